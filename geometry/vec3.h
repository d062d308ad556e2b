#pragma once
// Points and directions in double precision; the physics never leaves doubles.
#include <Eigen/Core>
#include <Eigen/Geometry>  // cross products of Vec3
#include <limits>

namespace beampack {

using Vec3 = Eigen::Vector3d;

struct Box {
  Vec3 lower{Vec3::Constant(std::numeric_limits<double>::infinity())};
  Vec3 upper{Vec3::Constant(-std::numeric_limits<double>::infinity())};

  bool empty() const { return (lower.array() > upper.array()).any(); }
  void grow(const Vec3& p, double r) {
    lower = lower.cwiseMin(p - Vec3::Constant(r));
    upper = upper.cwiseMax(p + Vec3::Constant(r));
  }
  bool contains(const Vec3& p) const {
    return (p.array() >= lower.array()).all() && (p.array() <= upper.array()).all();
  }
};

}  // namespace beampack
