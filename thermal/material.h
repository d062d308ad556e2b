#pragma once
// Thermal properties of one material (paper, sections 3-4; MODEL.md section 4).
#include <string>

namespace beampack {

struct Material {
  double density = 1000;           // rho, kg/m^3
  double c_solid = 1000;           // C_S, J/(kg K)
  double c_liquid = 2000;          // C_L, J/(kg K)
  double conductivity = 0;         // K, W/(m K)
  double melt_temperature = 600;   // theta_m, K
  double vapor_temperature = 700;  // theta_v, K
  // Latent-heat bands delta P / delta theta, J/(kg K): added to C during a step that crosses the
  // transformation temperature (paper, section 4), which is what holds the temperature back.
  double latent_melt = 1000;      // S -> L
  double latent_solidify = 1000;  // L -> S
  double latent_vapor = 1000;     // L -> V

  // InputError naming the key, the value and the limit, e.g.
  // "material.conductivity = -3: must be >= 0". `prefix` names the table ("material",
  // "material[1]").
  void validate(const std::string& prefix = "material") const;
};

// m min(C_S, C_L) / M of a particle of this volume: its least thermal mass in either phase, as the
// solver sees it with the time scaling M (thermal.time_scaling).
inline double least_thermal_mass(const Material& m, double volume, double time_scaling) {
  return m.density * volume * (m.c_solid < m.c_liquid ? m.c_solid : m.c_liquid) / time_scaling;
}

}  // namespace beampack
