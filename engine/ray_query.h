#pragma once
// What a nearest-hit query asks and answers, whichever structure runs it (EmbreeScene for
// primaries, SphereGrid for bounces): both give the same answer bit for bit, so the tracer hands
// either the same RayQuery. Apart from embree_scene.h so that the grid does not see Embree's scene.
#include <cstdint>
#include <limits>

#include "../geometry/vec3.h"

namespace beampack {

constexpr std::uint32_t kNoParticle = std::numeric_limits<std::uint32_t>::max();

// Double-precision ray data indexed by the ray ids a query names (not Embree's RTCRay::id, which
// is the ray's slot in the packet). The callback reads origin, direction and skip (the sphere the
// ray has just left: never hit, so no tnear fudge), and improves t_hit/particle. The caller sets
// t_hit to the longest distance of interest (infinity) and particle to kNoParticle before a
// query; after it, they hold the nearest outside hit.
struct RayQuery {
  const Vec3* origin = nullptr;
  const Vec3* direction = nullptr;  // unit
  const std::uint32_t* skip = nullptr;
  double* t_hit = nullptr;
  std::uint32_t* particle = nullptr;
  // Optional: the outward normal at the hit in double, entry_normal (geometry/ray_sphere.h):
  // (hit point - centre) / R, unit to the round-off of the hit point.
  Vec3* normal = nullptr;
};

}  // namespace beampack
