#pragma once
// The laser beam as a bundle of parallel rays (MODEL.md section 2, paper section 5).
#include <cstdint>
#include <string>
#include <vector>

#include "../geometry/error.h"
#include "../geometry/vec3.h"

namespace beampack {

// Far beyond it the pulse energy P tau, or the temperatures it gives, overflows.
inline constexpr Cap kPowerCap{1e20,
                               "W (1e5 times the most powerful lasers'; far beyond it the pulse "
                               "energy with pulses.duration, or the temperatures it gives, "
                               "overflows)"};

struct BeamSpec {
  double power = 6000.0;                // beam.power, W: sum_k I_k A_r = P
  double diameter_fraction = 0.3;       // beam.diameter_fraction: d_b / D
  std::size_t rays = 1000;              // beam.rays: N_r
  std::string sampling = "random";      // beam.sampling: random | stratified
  std::string profile = "exponential";  // beam.profile: exponential | flat | gaussian
  double decay = 2.0;                   // beam.decay: a of (5.1), I = I_0 exp(-a d / r_b)
  // beam.gaussian_width: w / r_b of I = I_0 exp(-2 d^2 / w^2). Default 1: the disk edge is the
  // 1/e^2 radius, the usual laser "beam radius", so the disk holds 86% of the untruncated beam.
  double gaussian_width = 1.0;
  std::uint64_t seed = 1;  // beam.seed (random sampling)
  // beam.resample: random sampling draws new rays for every pulse (pulse k: stream k of the
  // seed), so the sampling error averages out over the pulses; false: every pulse is pulse 0's.
  bool resample = false;
  Vec3 direction{1.0, 0.0, 0.0};  // beam.direction, unit (paper: +x)
};

struct Beam {
  Vec3 direction;         // unit
  Vec3 centre;            // centre of the entry disk: the entry face's centre (make_beam)
  double radius = 0.0;    // r_b
  double ray_area = 0.0;  // A_r = A_b / N_r
  double power = 0.0;     // P
  // On the entry disk (the tracer moves them upstream of all spheres), in spatial tiles: 16
  // consecutive rays form a small patch (coherent packets).
  std::vector<Vec3> origin;
  std::vector<double> intensity;  // I_k, W/m^2, normalised so that sum I_k A_r = P

  std::size_t size() const { return origin.size(); }
  // E_k = I_k A_r tau: the energy ray k carries in a pulse of duration tau (MODEL.md section 2).
  std::vector<double> ray_energies(double pulse_duration) const;
};

// Two unit vectors spanning the beam disk, perpendicular to the unit direction d:
// u = d x (x, or y for d near +-x), normalised; v = d x u.
void disk_axes(const Vec3& d, Vec3& u, Vec3& v);

// The axis of the unit direction d's largest component (the first on a tie): the beam enters the
// sample cube across it, by the face it meets most squarely (MODEL.md section 2).
int entry_axis(const Vec3& d);

// The frame of a polarised beam's field (optics.polarisation): u is +z projected onto the disk,
// or +x for a beam that enters by a z face, normalised; v = d x u. For the +x beam u = +z and
// v = -y. The frame turns continuously with d while the beam keeps its entry face (there the
// projected axis is at least 1/sqrt(2) long) and jumps only where the beam's spot moves to another
// face anyway. disk_axes' frame, which places the rays, jumps at |d_x| = 0.9, inside a face.
void polarisation_axes(const Vec3& d, Vec3& u, Vec3& v);

// InputError naming the first key out of its range or against another key.
void validate_beam(const BeamSpec& spec, double sample_size);

// make_beam's checks of pulse `pulse`'s draw (the spec, and a profile its rays can sample)
// without building the beam: no tiles, no origins.
void check_pulse_draw(const BeamSpec& spec, double sample_size, std::uint64_t pulse);

// Validates the spec (InputError naming the key) and samples the disk for pulse `pulse` (its own
// random stream when spec.resample, else pulse 0's). The disk is perpendicular to the direction,
// its centre at the centre of the entry face: the face the beam meets most squarely (across the
// axis of the direction's largest component), so an oblique beam's spot is centred on that face.
Beam make_beam(const BeamSpec& spec, double sample_size, std::uint64_t pulse = 0);

// The profile's shape f(d) = I(d) / I_0 at distance d from the axis, beam radius r_b.
double beam_profile(const BeamSpec& spec, double d, double beam_radius);

}  // namespace beampack
