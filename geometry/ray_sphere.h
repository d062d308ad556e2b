#pragma once
// Ray-sphere intersection, outside hits only, in the cancellation-free form
// (Haines et al., "Precision improvements for ray/sphere intersection", Ray Tracing Gems, ch. 7).
#include <algorithm>
#include <cmath>
#include <limits>

#include "vec3.h"

namespace beampack {

constexpr double kNoHit = std::numeric_limits<double>::infinity();

// How a ray (origin o, unit direction d) passes a sphere (c, r): the part of the entry test before
// its square root and division, so a caller can drop most spheres on it cheaply (the grid walk).
struct SphereApproach {
  double b;       // distance along d to the closest approach
  double c_term;  // |o - c|^2 - r^2: > 0 when the origin is outside
  double disc;    // r^2 - |closest-approach offset|^2: >= 0 when the line meets the sphere
  // The sphere lies ahead and the line meets it: an entry is possible (if the origin is outside).
  bool ahead_and_met() const { return (b > 0.0) & (disc >= 0.0); }
};

inline SphereApproach sphere_approach(const Vec3& o, const Vec3& d, const Vec3& c, double r) {
  const Vec3 f = o - c;
  const double b = -f.dot(d);
  const Vec3 perp = f + b * d;  // closest-approach offset, no b^2 - c cancellation
  return {b, f.squaredNorm() - r * r, r * r - perp.squaredNorm()};
}

// Distance t > 0 along d to the first point where the ray enters the sphere from outside, or
// kNoHit. A ray starting inside or on the sphere has no outside hit: it is leaving, and the
// caller skips the sphere it has just left anyway. Branch-free (every test is a select), so a
// caller's loop over several rays overlaps their square roots and divisions instead of stalling
// on a mispredicted early exit.
inline double ray_sphere_entry(const SphereApproach& a) {
  const double q = a.b + std::sqrt(std::max(a.disc, 0.0));  // far root, without cancellation
  // A hit needs the origin outside (c_term > 0; inside or on: leaving), the sphere ahead (b > 0)
  // and the line to meet it (disc >= 0); the near root is then c / q (Vieta).
  const bool hit = (a.c_term > 0.0) & a.ahead_and_met();
  return hit ? a.c_term / q : kNoHit;
}

inline double ray_sphere_entry(const Vec3& o, const Vec3& d, const Vec3& c, double r) {
  return ray_sphere_entry(sphere_approach(o, d, c, r));
}

// The outward normal at the entry point o + t d of sphere (c, r): (point - c) / r, unit to within
// the round-off of the point (make it unit with near_unit). Both scene searches use this one.
inline Vec3 entry_normal(const Vec3& o, const Vec3& d, double t, const Vec3& c, double r) {
  return (o + t * d - c) * (1.0 / r);
}

// v / |v| for a v whose length is already near 1 (an entry_normal, a unit direction reflected
// about a unit normal): then one Newton step for 1 / sqrt(|v|^2) from 1, no square root or
// division, relative error below 1e-16; otherwise (a point known to few digits) the division.
inline Vec3 near_unit(const Vec3& v) {
  const double s = v.squaredNorm();
  return std::abs(s - 1.0) < 1e-8 ? Vec3(v * (1.5 - 0.5 * s)) : Vec3(v / std::sqrt(s));
}

}  // namespace beampack
