#pragma once
// Output files of a run (INTERFACE.md). Every file is written to a temporary name in the same
// directory and renamed into place, so an interrupted run never leaves a half-written file.
#include <functional>
#include <ostream>
#include <string>
#include <vector>

#include "engine/tracer.h"
#include "geometry/particles.h"

namespace beampack::tools {

// Writes through `fill`, then renames; InputError if the directory is not writable.
void write_atomically(const std::string& path, const std::function<void(std::ostream&)>& fill);

// id,x,y,z,r,temperature_K,phase,absorbed_J for every particle, vaporised ones included.
void write_particles_csv(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J);

// A ParaView PolyData frame: points with radius, temperature, phase, absorbed energy, alive.
void write_particles_vtp(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J);
// Ray segments as lines, with the energy each carried.
void write_rays_vtp(const std::string& path, const std::vector<RaySegment>& segments);
// The .pvd series index over frames (file name relative to the .pvd, time).
void write_pvd(const std::string& path, const std::vector<std::pair<std::string, double>>& frames);

// The shortest text that reads back as the same double (std::to_chars): 0.064, not
// 0.064000000000000001.
std::string exact(double v);

}  // namespace beampack::tools
