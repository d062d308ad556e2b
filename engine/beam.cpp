#include "engine/beam.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <sstream>

#include "geometry/compensated_sum.h"
#include "geometry/error.h"
#include "geometry/random.h"

namespace beampack {
namespace {

template <class T>
[[noreturn]] void bad(const char* key, const T& value, const char* limit) {
  std::ostringstream out;
  out << "`" << key << "` = " << value << ": " << limit;
  throw InputError(out.str());
}

}  // namespace

void validate_beam(const BeamSpec& s, double sample_size) {
  if (!(s.power > 0.0) || !std::isfinite(s.power))
    bad("beam.power", s.power, "must be > 0 and finite");
  if (s.power > kPowerCap.limit) bad("beam.power", s.power, cap_limit(kPowerCap).c_str());
  if (!(s.diameter_fraction > 0.0) || !std::isfinite(s.diameter_fraction))
    bad("beam.diameter_fraction", s.diameter_fraction, "must be > 0 and finite");
  if (s.rays < 1 || s.rays > (std::size_t{1} << 31))
    bad("beam.rays", s.rays, "must be in [1, 2^31]");
  if (s.sampling != "random" && s.sampling != "stratified")
    bad("beam.sampling", s.sampling, "must be `random` or `stratified`");
  if (s.resample && s.sampling != "random")
    bad("beam.resample", "true", "needs `beam.sampling` = `random` (stratified rays are fixed)");
  if (s.profile != "exponential" && s.profile != "flat" && s.profile != "gaussian")
    bad("beam.profile", s.profile, "must be `exponential`, `flat` or `gaussian`");
  if (!(s.decay >= 0.0) || !std::isfinite(s.decay))
    bad("beam.decay", s.decay, "must be >= 0 and finite");
  if (!(s.gaussian_width > 0.0) || !std::isfinite(s.gaussian_width))
    bad("beam.gaussian_width", s.gaussian_width, "must be > 0 and finite");
  const double norm = s.direction.norm();
  if (!std::isfinite(norm) || std::abs(norm - 1.0) > 1e-9)
    bad("beam.direction", "|d| = " + shown_number(norm), "must be a unit vector");
  if (!(sample_size > 0.0) || !std::isfinite(sample_size))
    bad("sample.size", sample_size, "must be > 0 and finite");
}

namespace {

// Uniform in the unit disk: r = sqrt(xi), equal area per dr^2 (seeded, one stream per pulse).
std::vector<Eigen::Vector2d> random_disk(std::size_t n, std::uint64_t seed, std::uint64_t stream) {
  Rng rng = Rng::stream(seed, stream);
  std::vector<Eigen::Vector2d> p(n);
  for (auto& q : p) {
    const double r = std::sqrt(rng.uniform());
    const double phi = 2.0 * std::numbers::pi * rng.uniform();
    q = {r * std::cos(phi), r * std::sin(phi)};
  }
  return p;
}

// Deterministic equal-area sampling (Vogel's spiral): ray k sits at the mid-area radius of the
// k-th of N equal-area annuli, r_k = sqrt((k + 1/2) / N), turned by the golden angle each step.
// Every ray stands for area A_b / N; unlike rings of equal radius, no circle concentric with the
// beam (a sphere on the axis, the beam edge) lines up with many rays at once, so the quadrature
// error of such features falls like 1/N instead of 1/sqrt(N).
std::vector<Eigen::Vector2d> stratified_disk(std::size_t n) {
  const double golden_angle = std::numbers::pi * (3.0 - std::sqrt(5.0));
  std::vector<Eigen::Vector2d> p(n);
  for (std::size_t k = 0; k < n; ++k) {
    const double r = std::sqrt((static_cast<double>(k) + 0.5) / static_cast<double>(n));
    const double phi = golden_angle * static_cast<double>(k);
    p[k] = {r * std::cos(phi), r * std::sin(phi)};
  }
  return p;
}

// sum_k I_k A_r, compensated, in ray order (as the tracer's ledger sums the rays' energies): a
// plain sum of a flat beam's million equal terms drifts 3e-11 from the exact one, and normalising
// to it made the rays carry that much more or less than P.
double delivered_power(const std::vector<double>& intensity, double ray_area) {
  CompensatedSum sum;
  for (double i : intensity) sum.add(i * ray_area);
  return sum.value();
}

// Scale I_k = I_0 f_k with I_0 = P / (A_r sum f): sum I_k A_r = P (MODEL.md section 2). The
// largest ray then absorbs the round-off residual so the sum, taken in ray order, is P exactly, or
// an ulp of P from it where no intensity of that ray gives P (below).
// The shape is first scaled by a power of two that brings its largest value to [0.5, 1): rays
// only in a profile's far tail (f ~ 1e-307) made A_r sum f underflow and I_0 infinite, a NaN at
// the first hit. A power of two scales exactly, so every other beam keeps its bits.
void normalise(const BeamSpec& spec, std::vector<double>& intensity, double ray_area,
               double power) {
  const double f_max =
      intensity.empty() ? 0.0 : *std::max_element(intensity.begin(), intensity.end());
  constexpr const char* kZero = "too narrow a profile: it underflows to zero on every ray";
  if (!(f_max > 0.0) && spec.profile == "gaussian")
    bad("beam.gaussian_width", spec.gaussian_width, kZero);
  if (!(f_max > 0.0)) bad("beam.decay", spec.decay, kZero);
  int exponent = 0;
  std::frexp(f_max, &exponent);
  double shape_sum = 0.0;
  for (double& f : intensity) shape_sum += (f = std::ldexp(f, -exponent));
  const double i0 = power / (ray_area * shape_sum);
  if (!std::isnormal(ray_area) || !std::isfinite(i0)) {  // P / A: a beam narrower than physics
    std::ostringstream out;
    out << "`beam.diameter_fraction` = " << spec.diameter_fraction
        << " with `beam.power` = " << power << " W and " << spec.rays << " rays: each ray's area, "
        << ray_area
        << " m^2, is too small for double precision (the intensity P / area must stay finite, "
        << "the area a normal double); widen the beam or lower beam.power";
    throw InputError(out.str());
  }
  std::size_t largest = 0;
  for (std::size_t k = 0; k < intensity.size(); ++k) {
    intensity[k] *= i0;
    if (intensity[k] > intensity[largest]) largest = k;
  }
  // The residual steps land the sum on P in most beams, but not in one in nine of a few random
  // rays: the roundings of the partial sums after the largest ray (ties to even where a partial
  // sum enters a coarser binade) can move the sum two ulps at a time, and the steps jumped over P
  // and back, leaving it an ulp or two off. The sum is monotone in that ray's intensity: the two
  // sides of the jump bracket P, and a bisection over the doubles between them finds the intensity
  // that gives P, when one does, or else the one whose sum is nearest, an ulp off. (The steps run
  // first, as before: the beams they normalise keep their bits.)
  double& top = intensity[largest];
  double below = 0.0, above = 0.0, sum_below = 0.0, sum_above = 0.0;  // 0: that side not met yet
  for (int pass = 0; pass < 4; ++pass) {
    const double sum = delivered_power(intensity, ray_area);
    if (sum == power) return;
    (sum < power ? below : above) = top;
    (sum < power ? sum_below : sum_above) = sum;
    top += (power - sum) / ray_area;
  }
  if (below == 0.0 || above == 0.0) return;  // never across P: left where the steps ended
  // Positive doubles are ordered as their bit patterns.
  using Bits = std::uint64_t;
  for (;;) {
    const Bits low = std::bit_cast<Bits>(below), high = std::bit_cast<Bits>(above);
    const double middle = std::bit_cast<double>(low + (high - low) / 2);
    if (middle == below) break;
    top = middle;
    const double sum = delivered_power(intensity, ray_area);
    if (sum == power) return;
    (sum < power ? below : above) = middle;
    (sum < power ? sum_below : sum_above) = sum;
  }
  top = power - sum_below <= sum_above - power ? below : above;
}

constexpr std::size_t kTile = 16;  // rays per packet in the tracer

// Spatial tiles: the rays [begin, end) are split near the middle, at a multiple of kTile, across
// the longer side of their bounding box, and each half again, until a run is one tile. Every
// kTile consecutive rays are then a compact patch of the beam (a coherent packet), and
// consecutive tiles are neighbours. (A Morton order of random points, used before, lets some runs
// of 16 straddle a jump of the curve: measured, those split packets cost traversal time.)
// The order is fixed by the points alone, not by the standard library: nth_element leaves each
// half's order unspecified, so a finished tile is sorted (the sums over rays follow this order).
void tile(std::vector<Eigen::Vector2d>& points, std::size_t begin, std::size_t end) {
  const auto first = points.begin() + static_cast<std::ptrdiff_t>(begin);
  const auto last = points.begin() + static_cast<std::ptrdiff_t>(end);
  const auto along = [](int axis) {  // a total order on distinct points
    return [axis](const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
      return a[axis] < b[axis] || (a[axis] == b[axis] && a[1 - axis] < b[1 - axis]);
    };
  };
  if (end - begin <= kTile) {
    std::sort(first, last, along(0));
    return;
  }
  Eigen::Vector2d lower = points[begin], upper = points[begin];
  for (std::size_t k = begin; k < end; ++k)
    lower = lower.cwiseMin(points[k]), upper = upper.cwiseMax(points[k]);
  const int axis = (upper - lower).x() >= (upper - lower).y() ? 0 : 1;
  const std::size_t tiles = (end - begin + kTile - 1) / kTile;
  const std::size_t middle = begin + kTile * (tiles / 2);
  std::nth_element(first, points.begin() + static_cast<std::ptrdiff_t>(middle), last, along(axis));
  tile(points, begin, middle);
  tile(points, middle, end);
}

// Pulse `pulse`'s points in the unit disk (its own stream with beam.resample, else pulse 0's).
std::vector<Eigen::Vector2d> disk_points(const BeamSpec& spec, std::uint64_t pulse) {
  return spec.sampling == "random" ? random_disk(spec.rays, spec.seed, spec.resample ? pulse : 0)
                                   : stratified_disk(spec.rays);
}

// r_b = d_b / 2 with d_b = beam.diameter_fraction D.
double radius_of(const BeamSpec& spec, double sample_size) {
  return 0.5 * spec.diameter_fraction * sample_size;
}

// The centre of the face the beam enters by (MODEL.md section 2: the disk is centred on the
// entry face): the face it meets most squarely, across the axis of d's largest component (the
// first such axis on a tie). For a beam along an axis this is sample centre - (D/2) d.
Vec3 entry_face_centre(const Vec3& d, double size) {
  const int a = entry_axis(d);
  Vec3 centre = Vec3::Constant(0.5 * size);
  centre[a] = d[a] > 0.0 ? 0.0 : size;
  return centre;
}

// A_r = pi r_b^2 / N_r: the disk's area each ray stands for.
double ray_area(const BeamSpec& spec, double radius) {
  return std::numbers::pi * radius * radius / static_cast<double>(spec.rays);
}

}  // namespace

int entry_axis(const Vec3& d) {
  int a = 0;
  for (int k = 1; k < 3; ++k)
    if (std::abs(d[k]) > std::abs(d[a])) a = k;
  return a;
}

void polarisation_axes(const Vec3& d, Vec3& u, Vec3& v) {
  const Vec3 axis = entry_axis(d) == 2 ? Vec3::UnitX() : Vec3::UnitZ();
  u = (axis - axis.dot(d) * d).normalized();
  v = d.cross(u);
}

void disk_axes(const Vec3& d, Vec3& u, Vec3& v) {
  const Vec3 helper = std::abs(d.x()) < 0.9 ? Vec3(1, 0, 0) : Vec3(0, 1, 0);
  u = d.cross(helper).normalized();
  v = d.cross(u);
}

double beam_profile(const BeamSpec& spec, double d, double beam_radius) {
  if (spec.profile == "flat") return 1.0;
  if (spec.profile == "gaussian") {
    const double w = spec.gaussian_width * beam_radius;
    return std::exp(-2.0 * d * d / (w * w));
  }
  return std::exp(-spec.decay * d / beam_radius);  // (5.1), d normalised by r_b
}

void check_pulse_draw(const BeamSpec& spec, double sample_size, std::uint64_t pulse) {
  validate_beam(spec, sample_size);
  const double radius = radius_of(spec, sample_size);
  std::vector<double> intensity;
  intensity.reserve(spec.rays);
  for (const auto& q : disk_points(spec, pulse))
    intensity.push_back(beam_profile(spec, radius * q.norm(), radius));
  normalise(spec, intensity, ray_area(spec, radius), spec.power);
}

Beam make_beam(const BeamSpec& spec, double sample_size, std::uint64_t pulse) {
  validate_beam(spec, sample_size);
  Beam beam;
  beam.direction = spec.direction;
  beam.centre = entry_face_centre(spec.direction, sample_size);
  beam.radius = radius_of(spec, sample_size);
  beam.power = spec.power;
  beam.ray_area = ray_area(spec, beam.radius);
  auto unit = disk_points(spec, pulse);
  tile(unit, 0, unit.size());
  Vec3 u, v;
  disk_axes(spec.direction, u, v);
  beam.origin.reserve(spec.rays);
  beam.intensity.reserve(spec.rays);
  for (const auto& q : unit) {
    beam.origin.push_back(beam.centre + beam.radius * (q.x() * u + q.y() * v));
    beam.intensity.push_back(beam_profile(spec, beam.radius * q.norm(), beam.radius));
  }
  normalise(spec, beam.intensity, beam.ray_area, beam.power);
  return beam;
}

std::vector<double> Beam::ray_energies(double pulse_duration) const {
  if (!(pulse_duration > 0.0) || !std::isfinite(pulse_duration))
    bad("pulses.duration", pulse_duration, "must be > 0 and finite");
  std::vector<double> e(intensity.size());
  for (std::size_t k = 0; k < e.size(); ++k) e[k] = intensity[k] * ray_area * pulse_duration;
  return e;
}

}  // namespace beampack
