#pragma once
// The `quick` preset's scene for library tests: 200 spheres, 200 rays, 5 pulses long enough to
// melt and vaporise, with conduction.
#include "engine/simulation.h"

namespace beampack::testing {

inline SimulationSpec quick_scene() {
  SimulationSpec s;
  s.packing.sample_size = 1e-3;
  s.packing.count = 200;
  s.packing.seed = 7;
  s.beam.rays = 200;
  s.beam.seed = 7;
  s.pulses.count = 5;
  s.pulses.duration = 3e-13;
  s.materials[0].conductivity = 20.0;
  return s;
}

}  // namespace beampack::testing
