#pragma once
// IEEE floating-point mode for the physics. Embree's task observer turns on flush-to-zero and
// denormals-are-zero on the TBB threads that run its builds, and the setting stays with those
// threads. Double-precision code that then runs on a mix of threads would flush a denormal on one
// and keep it on another: results would depend on the thread count. This guard gives the code in
// its scope the IEEE default (no FTZ, no DAZ) and restores the thread's mode afterwards.
#if defined(__SSE__) || defined(_M_X64)
#include <xmmintrin.h>
#elif !defined(__aarch64__)
#error "beampack's float mode guard knows x86 (MXCSR) and arm64 (FPCR), the machines Embree runs on"
#endif

namespace beampack {
namespace float_mode {

#if defined(__SSE__) || defined(_M_X64)
using Word = unsigned;
// MXCSR: flush-to-zero (bit 15) and denormals-are-zero (bit 6).
constexpr Word kFlushBits = (1u << 15) | (1u << 6);
inline Word read() {
  return _mm_getcsr();
}
inline void write(Word w) {
  _mm_setcsr(w);
}
#else
using Word = unsigned long;
// FPCR: flush-to-zero (bit 24) covers both inputs and results.
constexpr Word kFlushBits = 1ul << 24;
inline Word read() {
  Word w;
  asm volatile("mrs %0, fpcr" : "=r"(w));
  return w;
}
inline void write(Word w) {
  asm volatile("msr fpcr, %0" : : "r"(w));
}
#endif

}  // namespace float_mode

class IeeeFloatMode {
 public:
  IeeeFloatMode() : saved_(float_mode::read()) {
    float_mode::write(saved_ & ~float_mode::kFlushBits);
  }
  ~IeeeFloatMode() { float_mode::write(saved_); }
  IeeeFloatMode(const IeeeFloatMode&) = delete;
  IeeeFloatMode& operator=(const IeeeFloatMode&) = delete;

 private:
  float_mode::Word saved_;
};

// Restores the calling thread's mode after a call that may change it (rtcCommitScene).
class KeepFloatMode {
 public:
  KeepFloatMode() : saved_(float_mode::read()) {}
  ~KeepFloatMode() { float_mode::write(saved_); }
  KeepFloatMode(const KeepFloatMode&) = delete;
  KeepFloatMode& operator=(const KeepFloatMode&) = delete;

 private:
  float_mode::Word saved_;
};

}  // namespace beampack
