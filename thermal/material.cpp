#include "thermal/material.h"

#include <cmath>
#include <sstream>

#include "geometry/error.h"

namespace beampack {

namespace {

void require(bool ok, const std::string& prefix, const char* key, double value, const char* limit) {
  if (ok) return;
  std::ostringstream msg;
  msg << prefix << '.' << key << " = " << value << ": " << limit;
  throw InputError(msg.str());
}

}  // namespace

void Material::validate(const std::string& prefix) const {
  // isfinite first: NaN and infinities fail every check below.
  require(std::isfinite(density) && density > 0, prefix, "density", density, "must be > 0");
  require(std::isfinite(c_solid) && c_solid > 0, prefix, "c_solid", c_solid, "must be > 0");
  require(std::isfinite(c_liquid) && c_liquid > 0, prefix, "c_liquid", c_liquid, "must be > 0");
  require(std::isfinite(conductivity) && conductivity >= 0, prefix, "conductivity", conductivity,
          "must be >= 0");
  require(std::isfinite(melt_temperature) && melt_temperature > 0, prefix, "melt_temperature",
          melt_temperature, "must be > 0");
  if (!(std::isfinite(vapor_temperature) && vapor_temperature > melt_temperature)) {
    std::ostringstream limit;
    limit << "must be > " << prefix << ".melt_temperature = " << melt_temperature;
    require(false, prefix, "vapor_temperature", vapor_temperature, limit.str().c_str());
  }
  require(std::isfinite(latent_melt) && latent_melt >= 0, prefix, "latent_melt", latent_melt,
          "must be >= 0");
  require(std::isfinite(latent_solidify) && latent_solidify >= 0, prefix, "latent_solidify",
          latent_solidify, "must be >= 0");
  require(std::isfinite(latent_vapor) && latent_vapor >= 0, prefix, "latent_vapor", latent_vapor,
          "must be >= 0");
}

}  // namespace beampack
