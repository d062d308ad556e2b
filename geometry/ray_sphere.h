#pragma once
// Ray-sphere intersection, outside hits only, in the cancellation-free form
// (Haines et al., "Precision improvements for ray/sphere intersection", Ray Tracing Gems, ch. 7).
#include <cmath>
#include <limits>

#include "geometry/vec3.h"

namespace beampack {

constexpr double kNoHit = std::numeric_limits<double>::infinity();

// Distance t > 0 along the unit direction d from origin o to the first point where the ray
// enters the sphere (c, r) from outside, or kNoHit. A ray starting inside or on the sphere has
// no outside hit: it is leaving, and the caller skips the sphere it has just left anyway.
inline double ray_sphere_entry(const Vec3& o, const Vec3& d, const Vec3& c, double r) {
  const Vec3 f = o - c;
  const double b = -f.dot(d);                 // distance along d to the closest approach
  const double c_term = f.squaredNorm() - r * r;
  if (!(c_term > 0.0) || b <= 0.0) return kNoHit;  // inside/on, or moving away
  const Vec3 perp = f + b * d;                // closest-approach offset, no b^2 - c cancellation
  const double disc = r * r - perp.squaredNorm();
  if (disc < 0.0) return kNoHit;
  const double q = b + std::sqrt(disc);       // far root, computed without cancellation
  return c_term / q;                          // near root = c / q (Vieta)
}

}  // namespace beampack
