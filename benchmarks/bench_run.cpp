// run/: the whole simulator on the paper's scene: one preset run, and the 13-value Table 1 sweep.
#include <benchmark/benchmark.h>

#include "engine/simulation.h"

namespace {

beampack::SimulationSpec zohdi2013(double conductivity) {
  // Mirrors the zohdi2013 preset of tools/presets.cpp (the library has no TOML reader).
  beampack::SimulationSpec s;
  s.packing.count = 1000;
  s.packing.radius_ratio = 0.325;
  s.packing.seed = 2013;
  s.beam.seed = 2013;
  s.pulses.count = 20;
  s.pulses.duration = 1e-13;
  s.materials[0].conductivity = conductivity;
  return s;
}

void run_preset(benchmark::State& state) {
  std::uint64_t segments = 0;
  for (auto _ : state) {
    beampack::Simulation sim(zohdi2013(100));
    sim.run();
    segments = sim.counts().segments;
  }
  state.counters["segments/s"] =
      benchmark::Counter(double(segments), benchmark::Counter::kIsIterationInvariantRate);
}

void run_table1_sweep(benchmark::State& state) {
  const double ks[] = {0, 1, 10, 20, 40, 60, 80, 100, 120, 140, 200, 300, 400};
  for (auto _ : state)
    for (double k : ks) {
      beampack::Simulation sim(zohdi2013(k));
      sim.run();
      benchmark::DoNotOptimize(sim.figures().vaporized_fraction);
    }
  state.counters["runs/s"] = benchmark::Counter(13, benchmark::Counter::kIsIterationInvariantRate);
}

}  // namespace

BENCHMARK(run_preset)->Name("run/zohdi2013")->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(run_table1_sweep)->Name("run/table1_sweep")->Unit(benchmark::kMillisecond)->UseRealTime();
