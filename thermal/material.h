#pragma once
// Thermal properties of one material (paper, sections 3-4; MODEL.md section 4).
#include <string>

#include "../geometry/error.h"

namespace beampack {

// Upper limits of the thermal inputs, physically generous, beyond which the arithmetic breaks.
// Measured with the quick preset (each key alone, or with walls within reach): conductivity 1e308
// and wall conductance 1e306 gave non-finite temperatures; latent heat 1e308 booked 1.6e280 J as
// stored of 8e-9 J absorbed, 1e25 (latent_melt) 4e-4 J, and the heat ledger opens by more than
// 1e-6 from ~1e14 (latent or specific heats alike: C + L is one capacity); a wall at 1e300 K
// booked -7.5e273 J, and conjugate gradients' residual turned NaN at 1e200 K. Density multiplies
// the thermal mass rho V C as the heat capacities do: the ledger closed to 7e-8 at rho = 1e12,
// 7e-7 at 1e13, and was open by 1.6e-4 at 1e15. At all these upper limits together the direct
// solver closes the ledger and the iterative ones stop with their own message. Not where a heat
// capacity at its lower cap meets bands or temperatures near their upper ones: the quick preset
// with C = 1e-12, latent bands of 1e12 and K = 1e20 still closes it to 6.6e-8 (below the run's
// 1e-6 warning), but with theta_m = 1e11, theta_v = 1e12 as well its particles keep a third of
// the heat absorbed, which the run's open-ledger warning says (thirty-sixth session; the phase
// review's 3.4e-6 and 116 times the heat were of a scene not recorded, before five sessions of
// changes to the heat step). The stiff scenes the project validates (K up to 1e6 in `beampack
// validate --stiff`, 1e9 in tests/test_thermal_stiff.cpp) are far inside.
inline constexpr Cap kConductivityCap{
    1e20,
    "W/(m K) (5e16 times diamond's; far larger ones overflow the conductances and the "
    "heat flows)"};
inline constexpr Cap kWallConductanceCap{
    1e20, "W/K per particle (far larger ones overflow the heat flows from the walls)"};
inline constexpr Cap kHeatCapacityCap{
    1e12,
    "J/(kg K) (2e8 times water's; beyond it a step's warming is lost to the "
    "temperatures' round-off: the heat ledger opens, and far beyond it books energies "
    "the beam never gave)"};
inline constexpr Cap kLatentBandCap{
    1e12,
    "J/(kg K) (a band's dP/dtheta, added to the specific heat inside it: 2e8 times water's "
    "specific heat; beyond it a step's warming is lost to the temperatures' round-off: the heat "
    "ledger opens, and far beyond it books energies the beam never gave)"};
inline constexpr Cap kTemperatureCap{
    1e12,
    "K (hotter than any solid or liquid; far higher ones overflow the heat flows, "
    "conductance times temperature difference)"};
inline constexpr Cap kDensityCap{
    1e12,
    "kg/m^3 (4e7 times osmium's; beyond it a step's warming is lost to the temperatures' "
    "round-off: the heat ledger opens)"};

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
  // "material.conductivity = -3: must be >= 0", or above its cap (kConductivityCap, ...).
  // `prefix` names the table ("material", "material[1]").
  void validate(const std::string& prefix = "material") const;
};

// m min(C_S, C_L) / M of a particle of this volume: its least thermal mass in either phase, as the
// solver sees it with the time scaling M (thermal.time_scaling).
inline double least_thermal_mass(const Material& m, double volume, double time_scaling) {
  return m.density * volume * (m.c_solid < m.c_liquid ? m.c_solid : m.c_liquid) / time_scaling;
}

}  // namespace beampack
