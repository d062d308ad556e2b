#include "engine/memory_need.h"

#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <iomanip>
#include <sstream>

#include "geometry/error.h"

namespace beampack {

// Peak resident set of `beampack run` (Release, one pulse, 2026-12-02): 448 MB with 10^6 rays,
// 1760 MB with 4 10^6 (437 bytes per ray); 57 MB with 10^5 particles, 468 MB with 10^6 (457 bytes
// per particle without conduction, 600 with). The contacts conduction needs: 141 bytes more per
// particle with K = 100, 58 with walls and K = 0 (526 MB). Rounded down: a bound that refuses only
// the hopeless. Without pulses (no ray state, no ray scene; 2026-12-03): 108 MB with 10^6
// particles, 413 MB with 4 10^6 (102 bytes per particle); no rays are drawn (2026-12-03).
constexpr double kBytesPerRay = 400;
constexpr double kBytesPerParticle = 400;
constexpr double kBytesPerParticleUntraced = 100;    // the particles alone
constexpr double kContactBytesWithWalls = 50;        // per particle, walls alone (K = 0)
constexpr double kContactBytesWithConduction = 100;  // per particle, conductivity > 0

namespace {

// The bytes a particle needs at least: itself (and its share of the ray scene when one is built),
// and the contacts when the set-up builds them.
double bytes_per_particle(const SimulationSpec& s) {
  const double contacts = !builds_contact_graph(s)        ? 0.0
                          : conducts_between_particles(s) ? kContactBytesWithConduction
                                                          : kContactBytesWithWalls;
  return (builds_ray_scene(s) ? kBytesPerParticle : kBytesPerParticleUntraced) + contacts;
}

// The bytes a ray of the beam needs at least: its state as it is traced; none without pulses.
double bytes_per_ray(const SimulationSpec& s) {
  return builds_ray_scene(s) ? kBytesPerRay : 0.0;
}

double need_of(const SimulationSpec& s, double particles) {
  return bytes_per_ray(s) * double(s.beam.rays) + bytes_per_particle(s) * particles;
}

// `particles` names the particles' count and where it came from; `lower` what to lower for them.
void refuse_need(const SimulationSpec& s, double available, double need,
                 const std::string& particles, const std::string& lower) {
  if (need <= available) return;
  const std::string rays = "`beam.rays` = " + std::to_string(s.beam.rays);
  const double ray_bytes = bytes_per_ray(s) * double(s.beam.rays);
  const bool by_rays = ray_bytes >= need - ray_bytes;
  const std::string with = need == ray_bytes ? "for its rays alone"
                           : ray_bytes == 0  ? "without pulses (no rays drawn)"
                                             : "with " + (by_rays ? particles : rays);
  std::ostringstream m;
  m << (by_rays ? rays : particles) << ": the run needs at least " << std::setprecision(3)
    << need / 1e9 << " GB " << with << " (";
  if (ray_bytes > 0) m << bytes_per_ray(s) << " bytes per ray, ";
  m << bytes_per_particle(s) << " bytes per particle"
    << (builds_contact_graph(s) ? " with its contacts" : "") << "), more than the "
    << available / 1e9 << " GB of this machine; lower " << (by_rays ? "`beam.rays`" : lower);
  throw InputError(m.str());
}

}  // namespace

double least_memory_need(const SimulationSpec& s, std::size_t file_particles) {
  return need_of(s, s.packing.source == "file" ? double(file_particles) : double(s.packing.count));
}

double machine_memory() {
  double bytes = double(sysconf(_SC_PHYS_PAGES)) * double(sysconf(_SC_PAGE_SIZE));
  std::ifstream limit("/sys/fs/cgroup/memory.max");  // "max" when there is none
  double cgroup = 0;
  if (limit >> cgroup && cgroup > 0) bytes = std::min(bytes, cgroup);
  return bytes;
}

void refuse_beyond_memory(const SimulationSpec& s, double available, std::size_t file_particles) {
  const bool file = s.packing.source == "file";
  const std::string particles = file ? "`packing.file` = \"" + s.packing.file + "\" (" +
                                           std::to_string(file_particles) + " particles)"
                                     : "`packing.count` = " + std::to_string(s.packing.count);
  refuse_need(s, available, least_memory_need(s, file_particles), particles,
              file ? "the particle count" : "`packing.count`");
}

void refuse_beyond_memory_of_given(const SimulationSpec& s, double available,
                                   std::size_t particles) {
  refuse_need(s, available, need_of(s, double(particles)),
              "the " + std::to_string(particles) + " particles given", "the particle count");
}

}  // namespace beampack
