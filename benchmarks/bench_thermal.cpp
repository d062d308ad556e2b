// One implicit thermal step (3.10) on the paper's packing (random-overlap, D = 1e-3 m, L = 0.325)
// with the paper's step dt = 0.05 R / c and M = 1e6: fixed-point against CG against LDL^T, at
// K = 100 and K = 1e5, and the cost against N for the exponent.
#include <benchmark/benchmark.h>

#include <cmath>
#include <map>
#include <memory>
#include <random>
#include <string>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

constexpr double kSize = 1e-3, kRatio = 0.325, kLight = 2.99792458e8, kXi = 0.05;

// Packing and contacts are the expensive part of the set-up: built once per N.
struct Scene {
  Particles particles;
  std::vector<Contact> contacts;
  std::vector<double> absorbed;
  double dt = 0;
};

const Scene& scene(std::size_t n) {
  static std::map<std::size_t, std::unique_ptr<Scene>> cache;
  auto& s = cache[n];
  if (s) return *s;
  s = std::make_unique<Scene>();
  s->particles = random_overlap_packing(n, kSize, kRatio, 1);
  // A field with something to conduct: temperatures in [300, 500] K, random heating ~10 K.
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (double& t : s->particles.temperature) t = 300.0 + 200.0 * u(rng);
  s->contacts = find_contacts(s->particles);
  const double r = s->particles.radius[0];
  s->dt = kXi * r / kLight;
  const double capacity = 1000.0 * 4.0 / 3.0 * 3.141592653589793 * r * r * r * 1000.0 / 1e6;
  for (std::size_t i = 0; i < n; ++i) s->absorbed.push_back(10.0 * capacity * u(rng));
  return *s;
}

void thermal_step(benchmark::State& state, std::string solver, double conductivity) {
  const auto n = static_cast<std::size_t>(state.range(0));
  const Scene& s = scene(n);
  Particles particles = s.particles;
  Material m;
  m.conductivity = conductivity;
  m.melt_temperature = 1e4;  // one conduction step, no phase change
  m.vapor_temperature = 2e4;
  ThermalSpec spec;
  spec.solver = solver;
  spec.time_scaling = 1e6;
  ThermalModel model(particles, {m}, spec);
  model.set_contacts(s.contacts);
  const ThermalModel::Snapshot start = model.save();
  StepReport report;
  int k = 0;
  for (auto _ : state) {
    // A slightly different dt each time: the direct solver refactorises (as after a phase
    // change) but keeps its symbolic analysis, the realistic per-step cost.
    try {
      report = model.step(s.dt * (1.0 + 1e-9 * (++k % 2)), s.absorbed);
    } catch (const RunError& e) {
      state.SkipWithError(e.what());
      break;
    }
    state.PauseTiming();
    model.restore(start);
    state.ResumeTiming();
  }
  state.counters["particles/s"] =
      benchmark::Counter(static_cast<double>(n), benchmark::Counter::kIsIterationInvariantRate);
  state.counters["iterations"] = report.iterations;
  state.counters["contraction"] = report.contraction_estimate;
  state.counters["contacts/particle"] = static_cast<double>(s.contacts.size()) / n;
  state.SetLabel(report.solver);
}

// What a beam leaves after a pulse: the packing at 300 K, heat (~10 K worth each) in the
// particles of the beam's cylinder (0.3 D wide) in the first fifth of the sample, none elsewhere.
// With skip_resting the step solves only the components the heat reached.
void thermal_beam_zone(benchmark::State& state, bool skip) {
  const auto n = static_cast<std::size_t>(state.range(0));
  const Scene& s = scene(n);
  Particles particles = s.particles;
  std::vector<double> absorbed(n, 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    particles.temperature[i] = 300.0;
    const Vec3& c = particles.centre[i];
    const double off_axis = std::hypot(c.y() - 0.5 * kSize, c.z() - 0.5 * kSize);
    if (off_axis < 0.15 * kSize && c.x() < 0.2 * kSize) absorbed[i] = s.absorbed[i];
  }
  Material m;
  m.conductivity = 100;
  m.melt_temperature = 1e4;  // one conduction step, no phase change
  m.vapor_temperature = 2e4;
  ThermalSpec spec;
  spec.skip_resting = skip;
  ThermalModel model(particles, {m}, spec);
  model.set_contacts(s.contacts);
  const ThermalModel::Snapshot start = model.save();
  StepReport report;
  for (auto _ : state) {
    report = model.step(s.dt, absorbed);
    state.PauseTiming();
    model.restore(start);
    state.ResumeTiming();
  }
  state.counters["solved_rows"] = static_cast<double>(report.solved_rows);
  state.SetLabel(report.solver);
}

[[maybe_unused]] const bool registered = [] {
  for (bool skip : {true, false})
    benchmark::RegisterBenchmark(
        skip ? "thermal/beam_zone/skip_resting/K:100" : "thermal/beam_zone/whole/K:100",
        thermal_beam_zone, skip)
        ->RangeMultiplier(10)
        ->Range(10000, 1000000)
        ->Unit(benchmark::kMillisecond)
        ->UseRealTime();
  for (double k : {100.0, 1e5})
    for (const char* solver : {"fixed-point", "cg", "direct", "auto"}) {
      const std::string name =
          std::string("thermal/step/") + solver + "/K:" + (k == 100.0 ? "100" : "1e5");
      benchmark::RegisterBenchmark(name.c_str(), thermal_step, std::string(solver), k)
          ->Arg(1000000)
          ->Unit(benchmark::kMillisecond)
          ->UseRealTime();
    }
  for (const char* solver : {"cg", "direct", "auto"})
    benchmark::RegisterBenchmark((std::string("thermal/scaling/") + solver + "/K:100").c_str(),
                                 thermal_step, std::string(solver), 100.0)
        ->RangeMultiplier(10)
        ->Range(1000, 1000000)
        ->Unit(benchmark::kMillisecond)
        ->UseRealTime();
  return true;
}();

}  // namespace
}  // namespace beampack
