// Analytic cases of the tracer and the heat step, run through the library as a user would.
#include <cmath>
#include <numbers>

#include "engine/fresnel.h"
#include "engine/simulation.h"
#include "geometry/contact.h"
#include "tools/run_config.h"
#include "tools/validate.h"

namespace beampack::tools {
namespace {

// A sphere of radius R in a collimated flat beam wider than it: the absorbed power is
// I * integral_0^R (1 - R_F(asin(r/R))) 2 pi r dr (single hit: reflected rays leave).
ValidationCase single_sphere() {
  const double D = 1e-3, R = 1e-4, n = 1.4, power = 100.0, tau = 1e-12;
  Particles p;
  p.add(Vec3(D / 2, D / 2, D / 2), R);
  BeamSpec beam;
  beam.power = power;
  beam.diameter_fraction = 0.4;  // disk radius 2e-4 > R
  beam.rays = 100000;
  beam.sampling = "stratified";
  beam.profile = "flat";
  const Beam b = make_beam(beam, D);
  OpticsSpec optics;
  optics.materials[0].n_solid = n;
  Tracer tracer(p, optics);
  tracer.launch(b, tau);
  std::vector<double> deposits;
  tracer.advance(std::numeric_limits<double>::infinity(), deposits);
  const double intensity = power / (std::numbers::pi * b.radius * b.radius);
  double integral = 0;
  const int m = 200000;  // midpoint rule in r
  for (int k = 0; k < m; ++k) {
    const double r = (k + 0.5) * R / m;
    const double cos_i = std::sqrt(std::max(0.0, 1 - (r / R) * (r / R)));
    integral += (1 - reflectance(cos_i, n)) * 2 * std::numbers::pi * r * (R / m);
  }
  const double expected = intensity * integral * tau;
  return {"single sphere, flat beam, 1e5 stratified rays: absorbed J", expected, deposits[0],
          1e-3 * expected};
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

// Two overlapping spheres: theta_1 - theta_2 decays as exp(-G (1/c1 + 1/c2) t).
ValidationCase two_particles() {
  Particles p;
  p.add(Vec3(0, 0, 0), 1e-4, 0, 500);
  p.add(Vec3(1.5e-4, 0, 0), 1e-4, 0, 300);
  Material material;
  material.conductivity = 50;
  ThermalSpec spec;
  spec.phi = 0.5;
  ThermalModel model(p, {material}, spec);
  const auto contacts = find_contacts(p);
  model.set_contacts(contacts);
  const double g = material.conductivity * contacts[0].area / contacts[0].distance;
  const double c = model.thermal_mass(0);
  const double rate = g * 2 / c, t_end = 2 / rate;
  const int steps = 2000;
  for (int s = 0; s < steps; ++s) model.step(t_end / steps, {});
  return {"two particles: (theta_1 - theta_2)(t) / (theta_1 - theta_2)(0)", std::exp(-rate * t_end),
          (p.temperature[0] - p.temperature[1]) / 200.0, 1e-5};
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
  std::vector<ValidationCase> cases{single_sphere(), lumped_model(), two_particles()};
  for (auto& c : ledgers()) cases.push_back(std::move(c));
  return cases;
}

}  // namespace beampack::tools
