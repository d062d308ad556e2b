#include "engine/state_io.h"

#include <algorithm>
#include <cstring>

namespace beampack {
namespace {

std::uint64_t fnv1a(const char* p, std::size_t n) {
  std::uint64_t h = 0xcbf29ce484222325ull;
  for (std::size_t i = 0; i < n; ++i) h = (h ^ static_cast<unsigned char>(p[i])) * 0x100000001b3ull;
  return h;
}

// The first bytes of every state: 0x01020304 as this machine stores it, then the sizes of the
// types the state is made of. Values are written in the machine's own layout, so a state from a
// machine of another byte order or type sizes is refused by name, before its checksum is read.
std::string layout_tag() {
  const std::uint32_t order = 0x01020304u;
  std::string tag(reinterpret_cast<const char*>(&order), sizeof order);
  for (std::size_t size : {sizeof(double), sizeof(std::size_t), sizeof(long double)})
    tag.push_back(static_cast<char>(size));
  return tag;
}

// Whether the last 8 bytes are the checksum of the rest, as with_checksum wrote them.
bool checksum_holds(const std::string& data) {
  std::uint64_t stored = 0;
  if (data.size() < sizeof stored) return false;
  std::memcpy(&stored, data.data() + data.size() - sizeof stored, sizeof stored);
  return fnv1a(data.data(), data.size() - sizeof stored) == stored;
}

}  // namespace

StateWriter::StateWriter() : buffer_(layout_tag()) {}

std::string with_checksum(std::string body) {
  const std::uint64_t h = fnv1a(body.data(), body.size());
  body.append(reinterpret_cast<const char*>(&h), sizeof h);
  return body;
}

std::string StateWriter::finish() const {
  return with_checksum(buffer_);
}

StateReader::StateReader(std::string data, std::string source)
    : data_(std::move(data)), source_(std::move(source)) {
  const std::string tag = layout_tag();
  if (data_.compare(0, tag.size(), tag) != 0) {
    std::string swapped = tag;
    std::reverse(swapped.begin(), swapped.begin() + 4);
    if (data_.compare(0, tag.size(), swapped) == 0)
      throw InputError(source_ +
                       ": checkpoint written on a machine of the other byte order; "
                       "checkpoints are read only where their byte order is native");
    // Sizes that differ in a state whose checksum holds: another build's; else a damaged header
    // (a flipped bit there, or a file of 6 bytes, was reported as another build's).
    if (data_.compare(0, 4, tag, 0, 4) == 0 && checksum_holds(data_))
      throw InputError(source_ +
                       ": checkpoint written with other sizes of double, size_t or long "
                       "double than this build's");
    damaged();
  }
  if (!checksum_holds(data_)) damaged();
  data_.resize(data_.size() - sizeof(std::uint64_t));
  pos_ = tag.size();
}

void StateReader::damaged() const {
  throw InputError(source_ + ": checkpoint is damaged or truncated (checksum or length mismatch)");
}

}  // namespace beampack
