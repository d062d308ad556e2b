#include "thermal/material.h"

#include <cmath>
#include <sstream>

#include "geometry/error.h"

namespace beampack {

namespace {

void require(bool ok, const std::string& prefix, const char* key, double value,
             const std::string& limit) {
  if (ok) return;
  std::ostringstream msg;
  msg << prefix << '.' << key << " = " << value << ": " << limit;
  throw InputError(msg.str());
}

// value within (0 or above, as `positive` says) and at most the cap; NaN and infinities fail.
void require_within(double value, bool positive, const Cap& cap, const std::string& prefix,
                    const char* key) {
  require(std::isfinite(value) && (positive ? value > 0 : value >= 0), prefix, key, value,
          positive ? "must be > 0" : "must be >= 0");
  require(value <= cap.limit, prefix, key, value, cap_limit(cap));
}

}  // namespace

void Material::validate(const std::string& prefix) const {
  require_within(density, true, kDensityCap, prefix, "density");
  require_within(c_solid, true, kHeatCapacityCap, prefix, "c_solid");
  require_within(c_liquid, true, kHeatCapacityCap, prefix, "c_liquid");
  require_within(conductivity, false, kConductivityCap, prefix, "conductivity");
  require_within(melt_temperature, true, kTemperatureCap, prefix, "melt_temperature");
  if (!(std::isfinite(vapor_temperature) && vapor_temperature > melt_temperature)) {
    std::ostringstream limit;
    limit << "must be > " << prefix << ".melt_temperature = " << melt_temperature;
    require(false, prefix, "vapor_temperature", vapor_temperature, limit.str());
  }
  require(vapor_temperature <= kTemperatureCap.limit, prefix, "vapor_temperature",
          vapor_temperature, cap_limit(kTemperatureCap));
  require_within(latent_melt, false, kLatentBandCap, prefix, "latent_melt");
  require_within(latent_solidify, false, kLatentBandCap, prefix, "latent_solidify");
  require_within(latent_vapor, false, kLatentBandCap, prefix, "latent_vapor");
}

}  // namespace beampack
