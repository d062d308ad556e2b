#pragma once
// IEEE floating-point mode for the physics. Embree's task observer turns on flush-to-zero and
// denormals-are-zero on the TBB threads that run its builds, and the setting stays with those
// threads. Double-precision code that then runs on a mix of threads would flush a denormal on one
// and keep it on another: results would depend on the thread count. This guard gives the code in
// its scope the IEEE default (no FTZ, no DAZ) and restores the thread's mode afterwards.
#include <xmmintrin.h>

namespace beampack {

class IeeeFloatMode {
 public:
  IeeeFloatMode() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ & ~(kFlushToZero | kDenormalsAreZero)); }
  ~IeeeFloatMode() { _mm_setcsr(saved_); }
  IeeeFloatMode(const IeeeFloatMode&) = delete;
  IeeeFloatMode& operator=(const IeeeFloatMode&) = delete;

 private:
  static constexpr unsigned kFlushToZero = 1u << 15, kDenormalsAreZero = 1u << 6;
  unsigned saved_;
};

// Restores the calling thread's mode after a call that may change it (rtcCommitScene).
class KeepFloatMode {
 public:
  KeepFloatMode() : saved_(_mm_getcsr()) {}
  ~KeepFloatMode() { _mm_setcsr(saved_); }
  KeepFloatMode(const KeepFloatMode&) = delete;
  KeepFloatMode& operator=(const KeepFloatMode&) = delete;

 private:
  unsigned saved_;
};

}  // namespace beampack
