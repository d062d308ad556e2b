#pragma once
// The least memory a scene needs, checked before it is set up: beyond the machine's it would end
// in std::bad_alloc, or the kernel's out-of-memory kill, part way into the set-up.
#include <cstddef>
#include <string>

#include "engine/simulation.h"

namespace beampack {

// The least memory a scene needs, in bytes: its rays and its particles, at the bytes each that
// a run measured (BENCHMARKS.md, "Memory a run needs"). Less than a run takes, never more. A
// file packing counts `file_particles` (0 when it has not been read).
double least_memory_need(const SimulationSpec& s, std::size_t file_particles = 0);

// This machine's memory in bytes: the physical memory, or the control group's limit if lower.
double machine_memory();

// InputError naming the key that needs the most, when a scene needs more than `available` bytes.
// The particles are spec.packing's: packing.count's, or for a file `file_particles` once read.
void refuse_beyond_memory(const SimulationSpec& s, double available,
                          std::size_t file_particles = 0);
// The same for `particles` particles a caller gave (a Simulation built on its own Particles).
void refuse_beyond_memory_of_given(const SimulationSpec& s, double available,
                                   std::size_t particles);

}  // namespace beampack
