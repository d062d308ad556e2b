#pragma once
// Ray-sphere intersection, outside hits only, in the cancellation-free form
// (Haines et al., "Precision improvements for ray/sphere intersection", Ray Tracing Gems, ch. 7).
#include <algorithm>
#include <cmath>
#include <limits>

#include "geometry/vec3.h"

namespace beampack {

constexpr double kNoHit = std::numeric_limits<double>::infinity();

// Distance t > 0 along the unit direction d from origin o to the first point where the ray
// enters the sphere (c, r) from outside, or kNoHit. A ray starting inside or on the sphere has
// no outside hit: it is leaving, and the caller skips the sphere it has just left anyway.
// Branch-free (every test is a select), so a caller's loop over several rays overlaps their
// square roots and divisions instead of stalling on a mispredicted early exit.
inline double ray_sphere_entry(const Vec3& o, const Vec3& d, const Vec3& c, double r) {
  const Vec3 f = o - c;
  const double b = -f.dot(d);                 // distance along d to the closest approach
  const double c_term = f.squaredNorm() - r * r;
  const Vec3 perp = f + b * d;                // closest-approach offset, no b^2 - c cancellation
  const double disc = r * r - perp.squaredNorm();
  const double q = b + std::sqrt(std::max(disc, 0.0));  // far root, without cancellation
  // A hit needs the origin outside (c_term > 0; inside or on: leaving), the sphere ahead (b > 0)
  // and the line to meet it (disc >= 0); the near root is then c / q (Vieta).
  const bool hit = (c_term > 0.0) & (b > 0.0) & (disc >= 0.0);
  return hit ? c_term / q : kNoHit;
}

}  // namespace beampack
