#include "thermal/conduction.h"

#include <cmath>
#include <limits>
#include <numbers>
#include <sstream>

#include "geometry/error.h"

namespace beampack {

void Wall::validate(const std::string& prefix) const {
  auto fail = [&](const char* key, double value, const char* limit) {
    std::ostringstream msg;
    msg << prefix << '.' << key << " = " << value << ": " << limit;
    throw InputError(msg.str());
  };
  if (axis < 0 || axis > 2) fail("axis", axis, "must be 0 (x), 1 (y) or 2 (z)");
  if (!std::isfinite(position)) fail("position", position, "must be finite");
  if (!(std::isfinite(reach) && reach >= 0)) fail("reach", reach, "must be >= 0");
  if (!(std::isfinite(temperature) && temperature > 0))
    fail("temperature", temperature, "must be > 0");
  if (temperature > kTemperatureCap.limit)
    fail("temperature", temperature, cap_limit(kTemperatureCap).c_str());
  if (!std::isfinite(conductance)) fail("conductance", conductance, "must be finite (< 0: from K)");
  if (conductance > kWallConductanceCap.limit)
    fail("conductance", conductance, cap_limit(kWallConductanceCap).c_str());
}

// A sphere tangent to the face (a lattice at L = 0.5 has a layer on each face) has a gap of 0 only
// up to the round-off of the coordinates: it touches within that, or a lattice's x- face would
// touch its layer and the x+ face not.
bool touches(const Wall& w, const Particles& p, std::size_t i) {
  const double x = p.centre[i][w.axis], r = p.radius[i];
  const double round_off =
      8 * std::numeric_limits<double>::epsilon() * (std::abs(x) + std::abs(w.position) + r);
  return std::abs(x - w.position) - r <= w.reach + round_off;
}

bool WallCoupling::any() const {
  for (double g : conductance)
    if (g > 0) return true;
  return false;
}

WallCoupling wall_coupling(const Particles& p, const std::vector<Material>& materials,
                           const std::vector<Wall>& walls) {
  WallCoupling out{std::vector<double>(p.size(), 0.0), std::vector<double>(p.size(), 0.0)};
  for (const Wall& w : walls) {
    for (std::size_t i = 0; i < p.size(); ++i) {
      if (!touches(w, p, i)) continue;
      const double g = w.conductance >= 0
                           ? w.conductance
                           : std::numbers::pi * materials[p.material[i]].conductivity * p.radius[i];
      out.conductance[i] += g;
      out.source[i] += g * w.temperature;
    }
  }
  return out;
}

std::vector<double> contact_conductances(const Particles& p, const std::vector<Material>& materials,
                                         const std::vector<Contact>& contacts) {
  std::vector<double> g(contacts.size());
  for (std::size_t e = 0; e < contacts.size(); ++e) {
    const Contact& c = contacts[e];
    g[e] = conductance(materials[p.material[c.i]].conductivity,
                       materials[p.material[c.j]].conductivity, c.area, c.distance);
    // A NaN or inf here would poison the solve: ThermalModel::set_contacts refuses the contacts
    // that give one, by name (an InputError, not an internal check: a caller's contacts).
  }
  return g;
}

Eigen::SparseMatrix<double> conduction_matrix(const Particles& p,
                                              const std::vector<Contact>& contacts,
                                              const std::vector<double>& g,
                                              const std::vector<double>& wall_g) {
  const auto n = static_cast<Eigen::Index>(p.size());
  std::vector<Eigen::Triplet<double>> t;
  t.reserve(p.size() + 4 * contacts.size());
  for (Eigen::Index i = 0; i < n; ++i)
    t.emplace_back(i, i, p.alive[i] && !wall_g.empty() ? wall_g[i] : 0.0);
  for (std::size_t e = 0; e < contacts.size(); ++e) {
    const Contact& c = contacts[e];
    const double v = p.alive[c.i] && p.alive[c.j] ? g[e] : 0.0;
    const int i = static_cast<int>(c.i), j = static_cast<int>(c.j);
    t.emplace_back(i, i, v);
    t.emplace_back(j, j, v);
    t.emplace_back(i, j, -v);
    t.emplace_back(j, i, -v);
  }
  Eigen::SparseMatrix<double> m(n, n);
  m.setFromTriplets(t.begin(), t.end());
  return m;
}

}  // namespace beampack
