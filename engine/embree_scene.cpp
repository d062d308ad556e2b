// The only file that includes Embree (STYLE.md point 2).
#include "engine/embree_scene.h"

#include <embree3/rtcore.h>

#include <algorithm>
#include <cmath>
#include <mutex>
#include <numeric>
#include <string>

#include "geometry/error.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
// Relative pad on float bounds and culling distances: float rounding of origins (~6e-8 of the
// coordinates) and of Embree's slab tests stays far below it, so no double hit is culled.
constexpr double kFloatPad = 1e-6;

// One user geometry: a set of particles. ids == nullptr means primID is the particle id.
struct SphereSet {
  const Vec3* centre;
  const double* radius;
  const std::uint8_t* removed;
  const std::uint32_t* ids;
  std::uint32_t particle(unsigned prim) const { return ids ? ids[prim] : prim; }
};

// RTCIntersectContext extended with the double side arrays (Embree passes it to the callbacks
// untouched; base must be the first member).
struct QueryContext {
  RTCIntersectContext base;
  RayQuery query;
  double slack;  // absolute pad of the float culling distance
};

float round_down(double x) {
  float f = static_cast<float>(x);
  return f > x ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}
float round_up(double x) {
  float f = static_cast<float>(x);
  return f < x ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}

// Bounds, rounded outward; a removed sphere gets empty bounds (dropped by builds and refits).
void sphere_bounds(const RTCBoundsFunctionArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  const std::uint32_t p = set->particle(args->primID);
  RTCBounds* b = args->bounds_o;
  if (set->removed[p]) {
    b->lower_x = b->lower_y = b->lower_z = std::numeric_limits<float>::infinity();
    b->upper_x = b->upper_y = b->upper_z = -std::numeric_limits<float>::infinity();
    return;
  }
  const Vec3& c = set->centre[p];
  const double r = set->radius[p];
  const double pad = r + kFloatPad * (r + c.cwiseAbs().maxCoeff());
  b->lower_x = round_down(c.x() - pad);
  b->lower_y = round_down(c.y() - pad);
  b->lower_z = round_down(c.z() - pad);
  b->upper_x = round_up(c.x() + pad);
  b->upper_y = round_up(c.y() + pad);
  b->upper_z = round_up(c.z() + pad);
}

// Double test of sphere p against ray id; true when it beats the ray's best hit so far.
// Ties in t go to the lower particle id so the answer does not depend on traversal order.
bool improve_hit(const QueryContext& ctx, const SphereSet& set, std::uint32_t p,
                 unsigned id, double& t_out) {
  const RayQuery& q = ctx.query;
  if (q.skip[id] == p) return false;  // the sphere the ray has just left
  const double t = ray_sphere_entry(q.origin[id], q.direction[id], set.centre[p], set.radius[p]);
  if (!(t < kNoHit)) return false;
  if (t < q.t_hit[id] || (t == q.t_hit[id] && p < q.particle[id])) {
    t_out = t;
    return true;
  }
  return false;
}

void sphere_intersect(const RTCIntersectFunctionNArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  const std::uint32_t p = set->particle(args->primID);
  if (set->removed[p]) return;
  const auto& ctx = *reinterpret_cast<const QueryContext*>(args->context);
  const unsigned n = args->N;
  RTCRayN* rays = RTCRayHitN_RayN(args->rayhit, n);
  RTCHitN* hits = RTCRayHitN_HitN(args->rayhit, n);
  for (unsigned i = 0; i < n; ++i) {
    if (args->valid[i] != -1) continue;
    const unsigned id = RTCRayN_id(rays, n, i);
    double t;
    if (!improve_hit(ctx, *set, p, id, t)) continue;
    ctx.query.t_hit[id] = t;
    ctx.query.particle[id] = p;
    // Float culling distance padded upward: Embree may still offer spheres the double test
    // finds nearer; it must never cull them.
    RTCRayN_tfar(rays, n, i) = round_up(t * (1.0 + kFloatPad) + ctx.slack);
    RTCHitN_primID(hits, n, i) = args->primID;
    RTCHitN_geomID(hits, n, i) = args->geomID;
    RTCHitN_instID(hits, n, i, 0) = args->context->instID[0];
    RTCHitN_u(hits, n, i) = 0.0f;
    RTCHitN_v(hits, n, i) = 0.0f;
    const Vec3 normal = (ctx.query.origin[id] + t * ctx.query.direction[id] - set->centre[p]);
    RTCHitN_Ng_x(hits, n, i) = static_cast<float>(normal.x());
    RTCHitN_Ng_y(hits, n, i) = static_cast<float>(normal.y());
    RTCHitN_Ng_z(hits, n, i) = static_cast<float>(normal.z());
  }
}

// Shadow query: any outside hit nearer than query.t_hit[id].
void sphere_occluded(const RTCOccludedFunctionNArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  const std::uint32_t p = set->particle(args->primID);
  if (set->removed[p]) return;
  const auto& ctx = *reinterpret_cast<const QueryContext*>(args->context);
  const unsigned n = args->N;
  for (unsigned i = 0; i < n; ++i) {
    if (args->valid[i] != -1) continue;
    const unsigned id = RTCRayN_id(args->ray, n, i);
    const RayQuery& q = ctx.query;
    if (q.skip[id] == p) continue;
    const double t = ray_sphere_entry(q.origin[id], q.direction[id], set->centre[p], set->radius[p]);
    if (t < q.t_hit[id]) {
      q.particle[id] = p;
      RTCRayN_tfar(args->ray, n, i) = -std::numeric_limits<float>::infinity();
    }
  }
}

void record_error(void* user, RTCError code, const char* message) {
  auto* impl_error = static_cast<std::pair<std::mutex, std::string>*>(user);
  std::lock_guard lock(impl_error->first);
  impl_error->second += "Embree error " + std::to_string(static_cast<int>(code)) + ": " +
                        (message ? message : "(no message)") + "; ";
}

}  // namespace

struct EmbreeScene::Impl {
  // Errors are recorded by the callback and thrown by check() on the calling thread, so no
  // exception ever unwinds through Embree's C interface.
  std::pair<std::mutex, std::string> error;
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  std::vector<SphereSet> sets;                       // one per geometry
  std::vector<std::vector<std::uint32_t>> brick_ids;  // particle ids per brick (bricks mode)
  std::vector<std::uint32_t> brick_of;               // brick of each particle (bricks mode)
  std::vector<RTCGeometry> geometries;
  double slack = 0.0;

  void check(const char* what) {
    std::lock_guard lock(error.first);
    if (!error.second.empty()) {
      std::string message = std::string(what) + ": " + error.second;
      error.second.clear();
      throw RunError(message);
    }
  }

  ~Impl() {
    for (RTCGeometry g : geometries) rtcReleaseGeometry(g);
    if (scene) rtcReleaseScene(scene);
    if (device) rtcReleaseDevice(device);
  }
};

namespace {

// Spatial bricks: particles sorted into a grid of cells holding ~per_brick particles each.
std::vector<std::vector<std::uint32_t>> make_bricks(const Particles& particles,
                                                    std::size_t per_brick) {
  const std::size_t n = particles.size();
  const Box box = particles.bounds();
  const std::size_t cells = std::max<std::size_t>(1, n / std::max<std::size_t>(1, per_brick));
  const int k = std::max(1, static_cast<int>(std::lround(std::cbrt(static_cast<double>(cells)))));
  std::vector<std::vector<std::uint32_t>> bricks(static_cast<std::size_t>(k) * k * k);
  const Vec3 extent = (box.upper - box.lower).cwiseMax(Vec3::Constant(1e-300));
  for (std::size_t i = 0; i < n; ++i) {
    int cell[3];
    for (int a = 0; a < 3; ++a) {
      const double u = box.empty() ? 0.0 : (particles.centre[i][a] - box.lower[a]) / extent[a];
      cell[a] = std::clamp(static_cast<int>(u * k), 0, k - 1);
    }
    bricks[(static_cast<std::size_t>(cell[2]) * k + cell[1]) * k + cell[0]].push_back(
        static_cast<std::uint32_t>(i));
  }
  std::erase_if(bricks, [](const auto& b) { return b.empty(); });
  return bricks;
}

}  // namespace

EmbreeScene::EmbreeScene(const Particles& particles, SceneUpdate update,
                         std::size_t particles_per_brick)
    : update_(update), impl_(std::make_unique<Impl>()) {
  removed_.resize(particles.size());
  for (std::size_t i = 0; i < particles.size(); ++i) removed_[i] = particles.alive[i] ? 0 : 1;
  Impl& im = *impl_;
  im.device = rtcNewDevice(nullptr);
  if (!im.device)
    throw RunError("Embree: rtcNewDevice failed (error " +
                   std::to_string(static_cast<int>(rtcGetDeviceError(nullptr))) + ")");
  rtcSetDeviceErrorFunction(im.device, record_error, &im.error);
  im.scene = rtcNewScene(im.device);
  const bool two_level = update != SceneUpdate::rebuild && update != SceneUpdate::mask_only;
  rtcSetSceneBuildQuality(im.scene, two_level ? RTC_BUILD_QUALITY_LOW : RTC_BUILD_QUALITY_MEDIUM);
  if (update == SceneUpdate::bricks) rtcSetSceneFlags(im.scene, RTC_SCENE_FLAG_DYNAMIC);

  if (update == SceneUpdate::bricks) {
    im.brick_ids = make_bricks(particles, particles_per_brick);
    im.brick_of.assign(particles.size(), 0);
    for (std::size_t b = 0; b < im.brick_ids.size(); ++b)
      for (std::uint32_t p : im.brick_ids[b]) im.brick_of[p] = static_cast<std::uint32_t>(b);
  } else {
    im.brick_ids.emplace_back();  // identity: primID is the particle id
  }
  im.sets.reserve(im.brick_ids.size());
  const Box box = particles.bounds();
  im.slack = box.empty() ? 0.0 : kFloatPad * (box.upper - box.lower).norm();
  for (const auto& ids : im.brick_ids) {
    const bool identity = update != SceneUpdate::bricks;
    im.sets.push_back({particles.centre.data(), particles.radius.data(), removed_.data(),
                       identity ? nullptr : ids.data()});
    RTCGeometry g = rtcNewGeometry(im.device, RTC_GEOMETRY_TYPE_USER);
    rtcSetGeometryUserPrimitiveCount(g, static_cast<unsigned>(identity ? particles.size() : ids.size()));
    rtcSetGeometryUserData(g, &im.sets.back());
    rtcSetGeometryBoundsFunction(g, sphere_bounds, nullptr);
    rtcSetGeometryIntersectFunction(g, sphere_intersect);
    rtcSetGeometryOccludedFunction(g, sphere_occluded);
    rtcSetGeometryBuildQuality(g, update == SceneUpdate::refit ? RTC_BUILD_QUALITY_REFIT
                                                               : RTC_BUILD_QUALITY_LOW);
    rtcCommitGeometry(g);
    rtcAttachGeometry(im.scene, g);
    im.geometries.push_back(g);
  }
  rtcCommitScene(im.scene);
  im.check("building the particle scene");
}

EmbreeScene::~EmbreeScene() = default;

void EmbreeScene::remove(std::span<const std::uint32_t> ids) {
  for (std::uint32_t p : ids) {
    if (p >= removed_.size())
      throw InputError("remove_particles: particle id " + std::to_string(p) + " >= count " +
                       std::to_string(removed_.size()));
    removed_[p] = 1;
  }
  if (ids.empty() || update_ == SceneUpdate::mask_only) return;
  Impl& im = *impl_;
  if (update_ == SceneUpdate::bricks) {
    std::vector<std::uint32_t> touched;
    touched.reserve(ids.size());
    for (std::uint32_t p : ids) touched.push_back(im.brick_of[p]);
    std::sort(touched.begin(), touched.end());
    touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
    for (std::uint32_t b : touched) rtcCommitGeometry(im.geometries[b]);
  } else {
    rtcCommitGeometry(im.geometries.front());
  }
  rtcCommitScene(im.scene);
  im.check("updating the particle scene");
}

namespace {

QueryContext make_context(const RayQuery& query, double slack, bool coherent) {
  QueryContext ctx;
  rtcInitIntersectContext(&ctx.base);
  ctx.base.flags = coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT
                            : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  ctx.query = query;
  ctx.slack = slack;
  return ctx;
}

}  // namespace

void EmbreeScene::intersect1(const RayQuery& query, std::uint32_t id) const {
  QueryContext ctx = make_context(query, impl_->slack, false);
  RTCRayHit rh;
  const Vec3& o = query.origin[id];
  const Vec3& d = query.direction[id];
  rh.ray.org_x = static_cast<float>(o.x());
  rh.ray.org_y = static_cast<float>(o.y());
  rh.ray.org_z = static_cast<float>(o.z());
  rh.ray.dir_x = static_cast<float>(d.x());
  rh.ray.dir_y = static_cast<float>(d.y());
  rh.ray.dir_z = static_cast<float>(d.z());
  rh.ray.tnear = 0.0f;
  rh.ray.tfar = query.t_hit[id] < kInf ? round_up(query.t_hit[id] * (1.0 + kFloatPad) + impl_->slack)
                                      : std::numeric_limits<float>::infinity();
  rh.ray.time = 0.0f;
  rh.ray.mask = 0xFFFFFFFFu;
  rh.ray.id = id;
  rh.ray.flags = 0;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(impl_->scene, &ctx.base, &rh);
}

void EmbreeScene::intersect16(const RayQuery& query, const std::uint32_t* ids, int count) const {
  QueryContext ctx = make_context(query, impl_->slack, true);
  alignas(64) RTCRayHit16 rh;
  alignas(64) int valid[16];
  for (int i = 0; i < 16; ++i) {
    valid[i] = i < count ? -1 : 0;
    const std::uint32_t id = i < count ? ids[i] : ids[0];
    const Vec3& o = query.origin[id];
    const Vec3& d = query.direction[id];
    rh.ray.org_x[i] = static_cast<float>(o.x());
    rh.ray.org_y[i] = static_cast<float>(o.y());
    rh.ray.org_z[i] = static_cast<float>(o.z());
    rh.ray.dir_x[i] = static_cast<float>(d.x());
    rh.ray.dir_y[i] = static_cast<float>(d.y());
    rh.ray.dir_z[i] = static_cast<float>(d.z());
    rh.ray.tnear[i] = 0.0f;
    rh.ray.tfar[i] = query.t_hit[id] < kInf
                         ? round_up(query.t_hit[id] * (1.0 + kFloatPad) + impl_->slack)
                         : std::numeric_limits<float>::infinity();
    rh.ray.time[i] = 0.0f;
    rh.ray.mask[i] = 0xFFFFFFFFu;
    rh.ray.id[i] = id;
    rh.ray.flags[i] = 0;
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  rtcIntersect16(valid, impl_->scene, &ctx.base, &rh);
}

bool EmbreeScene::occluded1(const RayQuery& query, std::uint32_t id) const {
  QueryContext ctx = make_context(query, impl_->slack, false);
  RTCRay ray;
  const Vec3& o = query.origin[id];
  const Vec3& d = query.direction[id];
  ray.org_x = static_cast<float>(o.x());
  ray.org_y = static_cast<float>(o.y());
  ray.org_z = static_cast<float>(o.z());
  ray.dir_x = static_cast<float>(d.x());
  ray.dir_y = static_cast<float>(d.y());
  ray.dir_z = static_cast<float>(d.z());
  ray.tnear = 0.0f;
  ray.tfar = query.t_hit[id] < kInf ? round_up(query.t_hit[id] * (1.0 + kFloatPad) + impl_->slack)
                                    : std::numeric_limits<float>::infinity();
  ray.time = 0.0f;
  ray.mask = 0xFFFFFFFFu;
  ray.id = id;
  ray.flags = 0;
  rtcOccluded1(impl_->scene, &ctx.base, &ray);
  return ray.tfar < 0.0f;
}

}  // namespace beampack
