#include "engine/state_io.h"

namespace beampack {
namespace {

std::uint64_t fnv1a(const char* p, std::size_t n) {
  std::uint64_t h = 0xcbf29ce484222325ull;
  for (std::size_t i = 0; i < n; ++i) h = (h ^ static_cast<unsigned char>(p[i])) * 0x100000001b3ull;
  return h;
}

}  // namespace

std::string StateWriter::finish() const {
  std::string out = buffer_;
  const std::uint64_t h = fnv1a(buffer_.data(), buffer_.size());
  out.append(reinterpret_cast<const char*>(&h), sizeof h);
  return out;
}

StateReader::StateReader(std::string data, std::string source)
    : data_(std::move(data)), source_(std::move(source)) {
  std::uint64_t stored = 0;
  if (data_.size() < sizeof stored) damaged();
  std::memcpy(&stored, data_.data() + data_.size() - sizeof stored, sizeof stored);
  data_.resize(data_.size() - sizeof stored);
  if (fnv1a(data_.data(), data_.size()) != stored) damaged();
}

void StateReader::damaged() const {
  throw InputError(source_ + ": checkpoint is damaged or truncated (checksum or length mismatch)");
}

}  // namespace beampack
