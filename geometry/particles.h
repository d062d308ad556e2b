#pragma once
// Particle state as a structure of flat arrays (LAMMPS' atom->x, atom->temperature).
// The thermal module indexes straight into these arrays; the ray scene keeps a packed copy of
// the spheres in Morton order (engine/embree_scene.h), with each one's index here.
#include <cstdint>
#include <span>
#include <vector>

#include "vec3.h"

namespace beampack {

enum class Phase : std::uint8_t { solid = 0, liquid = 1, vapor = 2 };

const char* phase_name(Phase phase);

struct Particles {
  std::vector<Vec3> centre;
  std::vector<double> radius;
  std::vector<std::uint16_t> material;
  std::vector<double> temperature;
  std::vector<Phase> phase;
  std::vector<std::uint8_t> alive;  // 0 once vaporised: never hit, never in contact again

  std::size_t size() const { return radius.size(); }
  bool empty() const { return radius.empty(); }
  void reserve(std::size_t n);
  std::size_t add(const Vec3& c, double r, std::uint16_t material_id = 0,
                  double temperature_K = 300.0);
  // Marks i vaporised; the scene and the contact graph must then be updated by their owners.
  void remove(std::size_t i);
  std::size_t alive_count() const;
  double max_radius() const;
  // Box around every live sphere (centre +- radius); empty when none is alive.
  Box bounds() const;
  double volume(std::size_t i) const;
};

// The ids a remove_particles names, each < count, checked before any is removed: InputError
// naming the first beyond.
void check_removal_ids(std::span<const std::uint32_t> ids, std::size_t count);

}  // namespace beampack
