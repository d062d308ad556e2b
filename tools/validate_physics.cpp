// Analytic cases of the tracer and the heat step, run through the library as a user would.
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

#include "engine/fresnel.h"
#include "engine/simulation.h"
#include "geometry/contact.h"
#include "tools/run_config.h"
#include "tools/validate.h"

namespace beampack::tools {
namespace {

// The energy one sphere of radius R at `centre` absorbs from one pulse of duration tau of the beam
// `spec` over a sample of size D, index n (single hit: reflected rays leave).
double traced_absorption(const BeamSpec& spec, double D, const Vec3& centre, double R, double n,
                         double tau) {
  Particles p;
  p.add(centre, R);
  OpticsSpec optics;
  optics.materials[0].n_solid = n;
  Tracer tracer(p, optics);
  tracer.launch(make_beam(spec, D), tau);
  std::vector<double> deposits;
  tracer.advance(std::numeric_limits<double>::infinity(), deposits);
  return deposits[0];
}

// tau * integral over the sphere's projected disk of (1 - R_F(theta_i)) I, in polar coordinates
// about the disk's centre, r = R sin u so that cos theta_i = cos u and r dr = R^2 sin u cos u du
// (smooth at the rim, where dr/du vanishes). `ring(r)` is the intensity integrated over the
// angle of the circle of radius r: 2 pi I for a uniform beam covering it. Midpoint rule in u.
template <class Ring>
double expected_absorption(double R, double n, double tau, const Ring& ring) {
  const int m = 200000;
  const double du = std::numbers::pi / 2 / m;
  double integral = 0;
  for (int k = 0; k < m; ++k) {
    const double u = (k + 0.5) * du;
    integral += (1 - reflectance(std::cos(u), n)) * ring(R * std::sin(u)) * R * R * std::sin(u) *
                std::cos(u) * du;
  }
  return integral * tau;
}

// The beam of section 2, its radius from the inputs: r_b = diameter_fraction D / 2.
BeamSpec stratified_beam(const char* profile, double power) {
  BeamSpec beam;
  beam.power = power;
  beam.diameter_fraction = 0.4;  // r_b = 2e-4 m in a 1 mm sample: twice the sphere's radius
  beam.rays = 100000;
  beam.sampling = "stratified";
  beam.profile = profile;
  return beam;
}

// One sphere in collimated beams, 1e5 stratified rays (Vogel's spiral, ~2.5e4 on the sphere),
// against the integral over its projected disk:
// - on the axis of a flat beam wider than it: I = P / (pi r_b^2);
// - on the axis of the exponential beam (5.1), I = I_0 exp(-a d / r_b), I_0 = P a^2 / (2 pi r_b^2
//   (1 - (1 + a) e^-a)) so that the disk carries P (MODEL.md section 2);
// - in a flat beam whose edge crosses it, its centre 1.5e-4 m off the axis: the circle of radius
//   r about its centre lies in the beam over the angle 2 acos((s^2 + r^2 - r_b^2) / (2 s r)).
// (Checked against independent quadratures in Python, Simpson's rule in r for the exponential
// beam and a two-dimensional one over the disk for the edge: the same to 8 digits.)
// Tolerances, relative, about 10 times the error the rays make (measured at 1e5 rays; at 2e5 to 1e6
// it stays within the same bounds): on the axis 1e-6 (flat 1.0e-7, exponential 2.9e-8: no sampled
// circle lines up with the sphere's rim); at the edge 1e-4 (1.7e-5 there, up to 2.7e-5 at other
// ray counts: the beam's own rim, which the outermost rays sample, cuts the sphere). So a beam
// radius off by 1e-6 (intensity by 2e-6) fails on the axis, and at the edge, where the absorbed
// energy changes by 7e3 of itself per m of offset, a beam 2e-8 m off centre fails.
std::vector<ValidationCase> single_sphere() {
  const double D = 1e-3, R = 1e-4, n = 1.4, power = 100.0, tau = 1e-12, a = 2.0, s = 1.5e-4;
  const double r_b = 0.4 * D / 2, pi = std::numbers::pi;
  const Vec3 axis(D / 2, D / 2, D / 2);  // the beam's axis (+x) through the entry face's centre
  const double flat = power / (pi * r_b * r_b);
  const double i0 = power * a * a / (2 * pi * r_b * r_b * (1 - (1 + a) * std::exp(-a)));
  const double on_flat = expected_absorption(R, n, tau, [&](double) { return 2 * pi * flat; });
  const double on_exp = expected_absorption(
      R, n, tau, [&](double r) { return 2 * pi * i0 * std::exp(-a * r / r_b); });
  const double at_edge = expected_absorption(R, n, tau, [&](double r) {
    const double c = (s * s + r * r - r_b * r_b) / (2 * s * r);
    return 2 * std::acos(std::clamp(c, -1.0, 1.0)) * flat;
  });
  const auto traced = [&](const char* profile, const Vec3& centre) {
    return traced_absorption(stratified_beam(profile, power), D, centre, R, n, tau);
  };
  return {{"single sphere, flat beam, on the axis: absorbed J", on_flat, traced("flat", axis),
           1e-6 * on_flat},
          {"single sphere, exponential beam (5.1), on the axis: absorbed J", on_exp,
           traced("exponential", axis), 1e-6 * on_exp},
          {"single sphere, flat beam, cut by its edge 1.5e-4 m off the axis: absorbed J", at_edge,
           traced("flat", axis + Vec3(0, s, 0)), 1e-4 * at_edge}};
}

// The lumped model (1.2): one particle between two isothermal walls under constant heating,
// Crank-Nicolson with 2000 steps over three time constants.
ValidationCase lumped_model() {
  const double radius = 1e-3, g_wall = 1e-3, theta_w = 300, M = 1e6;
  Material material;
  const double c =
      material.density * 4.0 / 3.0 * std::numbers::pi * std::pow(radius, 3) * material.c_solid / M;
  const double g_total = 2 * g_wall, power = 100 * g_total, tau = c / g_total, t_end = 3 * tau;
  Particles p;
  p.add(Vec3(radius, 0, 0), radius, 0, theta_w);
  ThermalSpec spec;
  spec.phi = 0.5;
  spec.time_scaling = M;
  for (double x : {0.0, 2 * radius}) spec.walls.push_back({0, x, 0.0, theta_w, g_wall});
  ThermalModel model(p, {material}, spec);
  const int steps = 2000;
  const double dt = t_end / steps;
  for (int s = 0; s < steps; ++s) model.step(dt, {power * dt});
  const double exact = theta_w + power / g_total * (1 - std::exp(-t_end / tau));
  return {"lumped model (1.2), Crank-Nicolson: theta(3 tau), K", exact, p.temperature[0], 1e-3};
}

// Two overlapping spheres of unequal radii: theta_1 - theta_2 decays as exp(-G (1/c1 + 1/c2) t),
// G = K A / d (3.2) with the lens area of (3.8)-(3.9) and c_i = rho (4/3) pi R_i^3 C_S / M, all
// computed here from the closed forms, so the case tests contact_geometry, the conductance and the
// integrator together. Crank-Nicolson, 2000 steps over G (1/c1 + 1/c2) t = 2: its error is
// e^-2 * 2 h^2 / 12 = 2.3e-8 at h = 1e-3; tolerance 1e-7. A contact area or a capacity off by
// 1e-6 relative moves the result by 2.7e-7.
ValidationCase two_particles() {
  const double r1 = 1e-4, r2 = 0.6e-4, d = 1.2e-4, pi = std::numbers::pi;
  Particles p;
  p.add(Vec3(0, 0, 0), r1, 0, 500);
  p.add(Vec3(d, 0, 0), r2, 0, 300);
  Material material;
  material.conductivity = 50;
  ThermalSpec spec;
  spec.phi = 0.5;
  ThermalModel model(p, {material}, spec);
  model.set_contacts(find_contacts(p));
  const double l1 = (d - (r2 * r2 - r1 * r1) / d) / 2;  // (3.9)
  const double area = pi * (r1 * r1 - l1 * l1);         // (3.8)
  const double g = material.conductivity * area / d;
  const auto capacity = [&](double r) {
    return material.density * 4.0 / 3.0 * pi * r * r * r * material.c_solid / spec.time_scaling;
  };
  const double rate = g * (1 / capacity(r1) + 1 / capacity(r2)), t_end = 2 / rate;
  const int steps = 2000;
  for (int k = 0; k < steps; ++k) model.step(t_end / steps, {});
  return {"two particles, radii 1e-4 and 6e-5 m: (theta_1 - theta_2)(t) / (theta_1 - theta_2)(0)",
          std::exp(-rate * t_end), (p.temperature[0] - p.temperature[1]) / 200.0, 1e-7};
}

// The `quick` preset: optics and heat ledgers close.
std::vector<ValidationCase> ledgers() {
  RunSources sources;
  sources.preset = "quick";
  Simulation sim(load_run_config(sources).sim);
  sim.run();
  const EnergyLedger e = sim.figures().energy;
  return {{"quick preset: optics ledger (injected - absorbed - escaped - cutoff) / injected", 0.0,
           e.optics_imbalance() / e.injected, 1e-12},
          {"quick preset: heat ledger |absorbed - stored - vaporized - walls| / the heat moved",
           0.0, e.heat_error(), 1e-8}};
}

}  // namespace

std::vector<ValidationCase> physics_cases() {
  std::vector<ValidationCase> cases = single_sphere();
  cases.push_back(lumped_model());
  cases.push_back(two_particles());
  for (auto& c : ledgers()) cases.push_back(std::move(c));
  return cases;
}

}  // namespace beampack::tools
