// beampack as a library: build a packing in code, run pulses, read temperatures.
// Build against an installed beampack with examples/CMakeLists.txt (find_package(beampack)).
#include <algorithm>
#include <cstdio>

#include <beampack/engine/simulation.h>

int main() {
  using namespace beampack;
  // A lattice of 8^3 spheres in a 1 mm cube, each overlapping its six neighbours (radius 0.55 of
  // the spacing, so the contacts conduct), hit by a flat beam along +x.
  SimulationSpec spec;
  spec.packing.sample_size = 1e-3;
  Particles particles = lattice_packing(512, spec.packing.sample_size, 0.55);
  spec.beam.rays = 2000;
  spec.beam.profile = "flat";
  spec.beam.sampling = "stratified";
  spec.materials[0].conductivity = 50;  // W/(m K)
  spec.pulses.count = 5;
  spec.pulses.duration = 1e-13;  // s: E_k = I_k A_r tau
  Simulation sim(spec, std::move(particles));
  sim.on_pulse_end([&](int pulse) {  // pulse: 0-based index; printed from 1 as history.csv does
    const Figures f = sim.figures();
    // max_temperature is empty only for a scene without particles; this one has 512.
    std::printf("pulse %d: peak %.1f K, vaporised %.4f, absorbed %.3e J of %.3e J\n", pulse + 1,
                f.max_temperature.value(), f.vaporized_fraction, f.energy.absorbed,
                f.energy.injected);
  });
  sim.run();
  const auto& t = sim.particles().temperature;
  std::printf("hottest particle: %.1f K\n", *std::max_element(t.begin(), t.end()));
  return 0;
}
