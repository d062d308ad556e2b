#pragma once
// Binary state for checkpoints: a layout tag (byte order, type sizes), then plain values and
// vectors of trivially copyable values in the machine's byte order, then an FNV-1a checksum, so
// a damaged file, or one from a machine of another byte order, is refused by name, not loaded.
#include <cstdint>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

#include "../geometry/error.h"

namespace beampack {

// `body` with its checksum appended: what StateWriter::finish gives for the bytes it wrote, and
// what StateReader checks.
std::string with_checksum(std::string body);

class StateWriter {
 public:
  StateWriter();
  template <class T>
  void value(const T& v) {
    static_assert(std::is_trivially_copyable_v<T>);
    bytes(&v, sizeof v);
  }
  template <class T, class A>
  void vector(const std::vector<T, A>& v) {
    value<std::uint64_t>(v.size());
    if (!v.empty()) bytes(v.data(), v.size() * sizeof(T));
  }
  void text(const std::string& s) {
    value<std::uint64_t>(s.size());
    bytes(s.data(), s.size());
  }
  // The buffer with its checksum appended.
  std::string finish() const;

 private:
  void bytes(const void* p, std::size_t n) { buffer_.append(static_cast<const char*>(p), n); }
  std::string buffer_;
};

class StateReader {
 public:
  // Checks the checksum; InputError naming `source` when the data is damaged or truncated.
  StateReader(std::string data, std::string source);
  template <class T>
  T value() {
    static_assert(std::is_trivially_copyable_v<T>);
    T v;
    bytes(&v, sizeof v);
    return v;
  }
  // The next value, left to be read.
  template <class T>
  T peek() {
    const std::size_t at = pos_;
    const T v = value<T>();
    pos_ = at;
    return v;
  }
  template <class T, class A>
  void vector(std::vector<T, A>& v) {
    const auto n = value<std::uint64_t>();
    if (n > (data_.size() - pos_) / std::max<std::size_t>(sizeof(T), 1)) damaged();
    v.resize(n);
    if (n) bytes(v.data(), n * sizeof(T));
  }
  std::string text() {
    const auto n = value<std::uint64_t>();
    if (n > data_.size() - pos_) damaged();
    std::string s(data_.data() + pos_, n);
    pos_ += n;
    return s;
  }

 private:
  void bytes(void* p, std::size_t n) {
    if (n > data_.size() - pos_) damaged();
    std::memcpy(p, data_.data() + pos_, n);
    pos_ += n;
  }
  [[noreturn]] void damaged() const;
  std::string data_, source_;
  std::size_t pos_ = 0;  // the constructor moves it past the layout tag
};

}  // namespace beampack
