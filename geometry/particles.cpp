#include "geometry/particles.h"

#include <algorithm>
#include <numbers>
#include <string>

#include "geometry/error.h"

namespace beampack {

const char* phase_name(Phase phase) {
  switch (phase) {
    case Phase::solid:
      return "solid";
    case Phase::liquid:
      return "liquid";
    case Phase::vapor:
      return "vapor";
  }
  return "unknown";
}

void Particles::reserve(std::size_t n) {
  centre.reserve(n);
  radius.reserve(n);
  material.reserve(n);
  temperature.reserve(n);
  phase.reserve(n);
  alive.reserve(n);
}

std::size_t Particles::add(const Vec3& c, double r, std::uint16_t material_id,
                           double temperature_K) {
  centre.push_back(c);
  radius.push_back(r);
  material.push_back(material_id);
  temperature.push_back(temperature_K);
  phase.push_back(Phase::solid);
  alive.push_back(1);
  return radius.size() - 1;
}

void check_removal_ids(std::span<const std::uint32_t> ids, std::size_t count) {
  for (std::uint32_t p : ids)
    if (p >= count)
      throw InputError("remove_particles: particle id " + std::to_string(p) + " >= count " +
                       std::to_string(count));
}

void Particles::remove(std::size_t i) {
  if (i >= size())
    throw InputError("Particles::remove: particle " + std::to_string(i) + " >= count " +
                     std::to_string(size()));
  alive[i] = 0;
  phase[i] = Phase::vapor;
}

std::size_t Particles::alive_count() const {
  return static_cast<std::size_t>(std::count(alive.begin(), alive.end(), std::uint8_t{1}));
}

double Particles::max_radius() const {
  double r = 0.0;
  for (std::size_t i = 0; i < size(); ++i)
    if (alive[i]) r = std::max(r, radius[i]);
  return r;
}

Box Particles::bounds() const {
  Box box;
  for (std::size_t i = 0; i < size(); ++i)
    if (alive[i]) box.grow(centre[i], radius[i]);
  return box;
}

double Particles::volume(std::size_t i) const {
  return 4.0 / 3.0 * std::numbers::pi * radius[i] * radius[i] * radius[i];
}

}  // namespace beampack
