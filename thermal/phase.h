#pragma once
// Phase change by latent-heat bands (paper, section 4; MODEL.md section 5 step 3): the heat
// capacity C_i of (4.1), and of (4.2) once phases change, chosen per step by the paper's five
// cases.
#include <cstdint>

#include "../geometry/particles.h"
#include "material.h"

namespace beampack {

// Bands a step theta_old -> theta_new crosses; a bit set, since one step may cross theta_m and
// theta_v together and then applies both.
enum PhaseBand : std::uint8_t { band_melt = 1, band_solidify = 2, band_vapor = 4 };

inline std::uint8_t crossed_bands(const Material& m, double theta_old, double theta_new) {
  std::uint8_t b = 0;
  if (theta_old < m.melt_temperature && theta_new >= m.melt_temperature) b |= band_melt;
  if (theta_old >= m.melt_temperature && theta_new < m.melt_temperature) b |= band_solidify;
  if (theta_old < m.vapor_temperature && theta_new >= m.vapor_temperature) b |= band_vapor;
  return b;
}

// C_i^K(t + dt) of (4.2) for a step that starts at theta_old: the capacity of the phase the step
// starts in (C_S below theta_m, C_L at or above, as in the paper's five cases after (4.1)) plus
// every band dP/dtheta crossed, which the re-solve of (4.1) adds.
inline double effective_heat_capacity(const Material& m, double theta_old, std::uint8_t bands) {
  double c = theta_old < m.melt_temperature ? m.c_solid : m.c_liquid;
  if (bands & band_melt) c += m.latent_melt;
  if (bands & band_solidify) c += m.latent_solidify;
  if (bands & band_vapor) c += m.latent_vapor;
  return c;
}

// Phase after a step: at or above theta_v vapour, at or above theta_m liquid, else solid.
inline Phase phase_at(const Material& m, double theta) {
  if (theta >= m.vapor_temperature) return Phase::vapor;
  return theta >= m.melt_temperature ? Phase::liquid : Phase::solid;
}

}  // namespace beampack
