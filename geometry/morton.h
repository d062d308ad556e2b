#pragma once
// Morton (Z-order) codes: particles sorted by them are near in memory where they are near in
// space, which is what the contact search, the conduction matrix and the ray scene read together.
#include <cstdint>

namespace beampack {

// Interleaves the low 21 bits of x, y and z: x in bits 0, 3, 6, ..., y in 1, 4, ..., z in 2, 5, ...
inline std::uint64_t morton_code(std::uint64_t x, std::uint64_t y, std::uint64_t z) {
  const auto spread = [](std::uint64_t v) {  // the low 21 bits of v to every third bit
    v &= 0x1fffff;
    v = (v | v << 32) & 0x1f00000000ffffull;
    v = (v | v << 16) & 0x1f0000ff0000ffull;
    v = (v | v << 8) & 0x100f00f00f00f00full;
    v = (v | v << 4) & 0x10c30c30c30c30c3ull;
    v = (v | v << 2) & 0x1249249249249249ull;
    return v;
  };
  return spread(x) | spread(y) << 1 | spread(z) << 2;
}

// The largest coordinate a code holds, 2^21 - 1.
constexpr double kMortonMax = double((1u << 21) - 1);

}  // namespace beampack
