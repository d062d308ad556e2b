#include "thermal/thermal_model.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <numeric>
#include <sstream>

#include "geometry/check.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "thermal/phase.h"

namespace beampack {

namespace {

// A name for a thermal state, unique across models (0: none, e.g. a checkpoint's).
std::uint64_t new_serial() {
  static std::atomic<std::uint64_t> serials{0};
  return ++serials;
}

// Wall time of work(), in seconds.
template <class Work>
double seconds_of(const Work& work) {
  const auto start = std::chrono::steady_clock::now();
  work();
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

template <class T>
[[noreturn]] void input_error(const char* key, const T& value, const std::string& limit) {
  std::ostringstream msg;
  msg << key << " = " << value << ": " << limit;
  throw InputError(msg.str());
}

}  // namespace

void ThermalSpec::validate() const {
  if (!(phi >= 0 && phi <= 1)) input_error("thermal.phi", phi, "must be in [0, 1]");
  if (!(std::isfinite(time_scaling) && time_scaling > 0))
    input_error("thermal.time_scaling", time_scaling, "must be > 0");
  if (time_scaling > kTimeScalingCap.limit)
    input_error("thermal.time_scaling", time_scaling, cap_limit(kTimeScalingCap));
  if (solver != "auto" && solver != "fixed-point" && solver != "cg" && solver != "direct")
    input_error("thermal.solver", '"' + solver + '"', "must be fixed-point, cg, direct or auto");
  if (!(tolerance > 0 && tolerance < 1))
    input_error("thermal.tolerance", tolerance, "must be in (0, 1)");
  if (max_iterations < 1) input_error("thermal.max_iterations", max_iterations, "must be >= 1");
  if (max_substeps < 1) input_error("thermal.max_substeps", max_substeps, "must be >= 1");
  if (max_phase_corrections < 1)
    input_error("thermal.max_phase_corrections", max_phase_corrections, "must be >= 1");
  for (std::size_t w = 0; w < walls.size(); ++w)
    walls[w].validate("thermal.walls[" + std::to_string(w) + "]");
}

ThermalModel::ThermalModel(Particles& particles, std::vector<Material> materials, ThermalSpec spec)
    : p_(particles),
      particle_count_(particles.size()),
      materials_(std::move(materials)),
      spec_(std::move(spec)) {
  serial_ = new_serial();
  check_particles(p_);
  spec_.validate();
  if (materials_.empty()) input_error("material", "(none)", "at least one material is needed");
  for (std::size_t k = 0; k < materials_.size(); ++k)
    materials_[k].validate(materials_.size() == 1 ? "material"
                                                  : "material[" + std::to_string(k) + "]");
  double coolest = std::numeric_limits<double>::infinity();  // of the live particles
  for (std::size_t i = 0; i < p_.size(); ++i) {
    if (p_.material[i] >= materials_.size())
      input_error(("particle " + std::to_string(i) + " material").c_str(), p_.material[i],
                  "must be < " + std::to_string(materials_.size()) + " (the number of materials)");
    if (!p_.alive[i]) continue;
    const Material& m = materials_[p_.material[i]];
    if (!(p_.temperature[i] < m.vapor_temperature))
      input_error(("particle " + std::to_string(i) + " temperature").c_str(), p_.temperature[i],
                  "must be < its material's vapor_temperature = " +
                      shown_number(m.vapor_temperature) + " K (it would start as vapour)");
    p_.phase[i] = phase_at(m, p_.temperature[i]);
    coolest = std::min(coolest, p_.temperature[i]);
  }
  walls_ = wall_coupling(p_, materials_, spec_.walls);
  has_walls_ = walls_.any();
  // Without walls the solve measures from the coolest live particle (0 K without one).
  reference_ = has_walls_               ? spec_.walls.front().temperature
               : std::isfinite(coolest) ? coolest
                                        : 0.0;
  stored_.assign(p_.size(), 0.0);
}

// The walls' terms, the matrices and the stored heat are of the particles as the model took
// them: a particle added since was read past their ends.
void ThermalModel::check_particle_count(const char* when) const {
  if (p_.size() != particle_count_)
    throw InputError(std::string("thermal ") + when + ": the particles were " +
                     std::to_string(particle_count_) + " when the heat model took them and are " +
                     std::to_string(p_.size()) + " now: a heat model's particles keep their count");
}

namespace {

[[noreturn]] void refuse_contact(const Contact& c, const std::string& what) {
  throw InputError("contact (" + std::to_string(c.i) + ", " + std::to_string(c.j) + "): " + what);
}

}  // namespace

// Refused whole before anything changes: a NaN area passed every "conducts" test as none (NaN > 0
// is false), a distance of 0 made an infinite conductance and a non-finite temperature.
void ThermalModel::set_contacts(const std::vector<Contact>& contacts) {
  check_particle_count("set_contacts");
  const bool same_pattern =
      contacts.size() == contacts_.size() &&
      std::equal(contacts.begin(), contacts.end(), contacts_.begin(),
                 [](const Contact& a, const Contact& b) { return a.i == b.i && a.j == b.j; });
  std::vector<std::uint32_t> degree(p_.size(), 0);
  std::size_t removed = 0;
  for (const Contact& c : contacts) {
    if (c.i >= p_.size() || c.j >= p_.size() || c.i == c.j)
      refuse_contact(c, "indices must be distinct and < " + std::to_string(p_.size()));
    if (!(std::isfinite(c.area) && c.area >= 0))
      refuse_contact(c, "area " + shown_number(c.area) + " m^2: must be finite and >= 0");
    if (!(std::isfinite(c.distance) && c.distance > 0))
      refuse_contact(c, "distance " + shown_number(c.distance) + " m: must be finite and > 0");
    ++degree[c.i], ++degree[c.j];
    removed += !p_.alive[c.i] || !p_.alive[c.j];
  }
  std::vector<double> g = contact_conductances(p_, materials_, contacts);
  for (std::size_t e = 0; e < g.size(); ++e)
    if (!std::isfinite(g[e]))
      refuse_contact(contacts[e], "conductance K A / d = " + shown_number(g[e]) + " W/K (area " +
                                      shown_number(contacts[e].area) + " m^2, distance " +
                                      shown_number(contacts[e].distance) + " m): must be finite");
  contacts_ = contacts;
  contact_degree_ = std::move(degree);
  removed_contacts_bound_ = removed;
  g_ = std::move(g);
  if (!same_pattern) all_.pattern_version = ++versions_;
  dirty_ = pattern_dirty_ = true;
}

void ThermalModel::drop_removed_contacts(double min_fraction) {
  check_particle_count("drop_removed_contacts");
  const double threshold = min_fraction * static_cast<double>(contacts_.size());
  const auto bound = static_cast<double>(removed_contacts_bound_);
  if (removed_contacts_bound_ == 0 || bound < threshold) return;  // fewer removed than that
  std::vector<Contact> live;
  live.reserve(contacts_.size());
  for (const Contact& c : contacts_)
    if (p_.alive[c.i] && p_.alive[c.j]) live.push_back(c);
  const double dead = static_cast<double>(contacts_.size() - live.size());
  if (dead > 0 && dead >= threshold) set_contacts(live);
  else removed_contacts_bound_ = contacts_.size() - live.size();
}

namespace {

// Where the stored entry (row, col) sits in the matrix's values (columns hold sorted rows).
Eigen::Index position_of(const SparseMatrix& m, Eigen::Index row, Eigen::Index col) {
  const int* begin = m.innerIndexPtr() + m.outerIndexPtr()[col];
  const int* end = m.innerIndexPtr() + m.outerIndexPtr()[col + 1];
  return std::lower_bound(begin, end, static_cast<int>(row)) - m.innerIndexPtr();
}

// Where each column's diagonal entry sits in the matrix's values, and the diagonal itself.
void find_diagonal(const SparseMatrix& m, std::vector<Eigen::Index>& pos,
                   Eigen::VectorXd& diagonal) {
  pos.resize(static_cast<std::size_t>(m.cols()));
  for (Eigen::Index j = 0; j < m.cols(); ++j) {
    pos[j] = position_of(m, j, j);
    diagonal[j] = m.valuePtr()[pos[j]];
  }
}

}  // namespace

// Rebuilds L + W when the contacts or the live set changed. K = 0 (no conducting contact)
// builds no matrix at all: the step is then diagonal. When only some particles' live flags
// changed (a vaporisation, a redo of the step), the work is in proportion to them and to their
// components, not to the packing.
void ThermalModel::assemble_if_needed() {
  if (!dirty_) return;
  System& s = all_;
  const bool conducts = live_contact_conducts();
  const bool in_place = !pattern_dirty_ && s.live.size() == p_.alive.size() &&
                        conducts == s.has_conduction && (!conducts || s.laplacian.nonZeros() > 0);
  if (in_place) {
    const std::vector<Eigen::Index> changed = live_flags_changed();
    for (Eigen::Index i : changed) set_wall_terms(i);
    // Components whose members changed (without conduction: the particles themselves).
    const std::vector<Eigen::Index> touched = conducts ? update_live_set(changed) : changed;
    if (restless_known_) restless_.insert(restless_.end(), touched.begin(), touched.end());
    for (Eigen::Index i : changed) {
      live_count_ += p_.alive[i] ? 1 : -1;
      s.live[i] = p_.alive[i];
    }
  } else {
    assemble_anew(conducts);
  }
  flipped_.clear(), flips_known_ = true;
  ++assembly_;
  dirty_ = false;
}

// The particles whose live flag differs from all_'s, ascending: from the record of the flags
// the model flipped itself (vaporisation, undo_step), or, after a restore, from every particle.
std::vector<Eigen::Index> ThermalModel::live_flags_changed() const {
  std::vector<Eigen::Index> changed;
  if (flips_known_) {
    changed = flipped_;
    std::sort(changed.begin(), changed.end());
    changed.erase(std::unique(changed.begin(), changed.end()), changed.end());
    std::erase_if(changed, [&](Eigen::Index i) { return all_.live[i] == p_.alive[i]; });
    return changed;
  }
  for (std::size_t i = 0; i < p_.size(); ++i)
    if (all_.live[i] != p_.alive[i]) changed.push_back(static_cast<Eigen::Index>(i));
  return changed;
}

// Some contact with G > 0 joins two live particles (after vaporisations there may be none left).
bool ThermalModel::live_contact_conducts() const {
  for (std::size_t e = 0; e < contacts_.size(); ++e)
    if (g_[e] > 0 && p_.alive[contacts_[e].i] && p_.alive[contacts_[e].j]) return true;
  return false;
}

// Particle i's wall terms in all_ (zero while it is not live); without conduction they are
// its whole diagonal.
void ThermalModel::set_wall_terms(Eigen::Index i) {
  System& s = all_;
  const bool live = p_.alive[i];
  s.wall_source[i] =
      live ? walls_.source[i] - walls_.conductance[i] * reference_ : 0.0;  // b relative to it
  s.wall_conductance[i] = live ? walls_.conductance[i] : 0.0;
  if (!s.has_conduction) s.diagonal[i] = s.wall_conductance[i];
}

void ThermalModel::assemble_anew(bool conducts) {
  const auto n = static_cast<Eigen::Index>(p_.size());
  System& s = all_;
  s.wall_source = Eigen::VectorXd::Zero(n);
  s.diagonal = Eigen::VectorXd::Zero(n);
  s.wall_conductance = Eigen::VectorXd::Zero(n);
  s.live = p_.alive;
  live_count_ = static_cast<std::size_t>(std::count(s.live.begin(), s.live.end(), 1));
  s.has_conduction = conducts;
  restless_known_ = false;  // contacts may have joined components: look at every particle
  for (Eigen::Index i = 0; i < n; ++i) set_wall_terms(i);
  if (conducts) {
    assemble_all();
    find_diagonal(s.laplacian, s.diag_pos, s.diagonal);
    find_components();
  } else {
    s.laplacian = SparseMatrix();
    pattern_dirty_ =
        false;  // no conducting contact: nothing to assemble until the live set changes
  }
}

// L + W from the contacts, and each off-diagonal's -G as if both ends were live.
void ThermalModel::assemble_all() {
  SparseMatrix& m = all_.laplacian;
  m = conduction_matrix(p_, contacts_, g_, walls_.conductance);
  contact_values_.assign(static_cast<std::size_t>(m.nonZeros()), 0.0);
  for (std::size_t e = 0; e < contacts_.size(); ++e) {
    const Contact& c = contacts_[e];
    contact_values_[static_cast<std::size_t>(position_of(m, c.i, c.j))] = -g_[e];
    contact_values_[static_cast<std::size_t>(position_of(m, c.j, c.i))] = -g_[e];
  }
  pattern_dirty_ = false;
}

// The columns of the particles whose live flag changed, and of their neighbours, recomputed in
// place as conduction_matrix builds them: the wall's G first, then each live neighbour's in
// ascending order (the contacts' order), so the values equal a new assembly bit for bit. The
// diagonal and the components of those particles follow. Returns those particles (ascending).
std::vector<Eigen::Index> ThermalModel::update_live_set(const std::vector<Eigen::Index>& changed) {
  SparseMatrix& m = all_.laplacian;
  std::vector<Eigen::Index> touched;
  for (Eigen::Index i : changed)
    for (SparseMatrix::InnerIterator it(m, i); it; ++it) touched.push_back(it.row());
  std::sort(touched.begin(), touched.end());
  touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
  double* values = m.valuePtr();
  for (Eigen::Index j : touched) {
    double diagonal = p_.alive[j] ? walls_.conductance[j] : 0.0;
    Eigen::Index at = -1;
    for (Eigen::Index k = m.outerIndexPtr()[j]; k < m.outerIndexPtr()[j + 1]; ++k) {
      const Eigen::Index r = m.innerIndexPtr()[k];
      if (r == j) {
        at = k;
        continue;
      }
      const double v =
          p_.alive[r] && p_.alive[j] ? contact_values_[static_cast<std::size_t>(k)] : 0.0;
      values[k] = v;
      diagonal += -v;
    }
    values[at] = all_.diagonal[j] = diagonal;
  }
  update_components(touched);
  return touched;
}

// Connected components of the live conducting contacts (union-find): each live particle's
// component is named by its lowest particle id, which also keeps the component's size and
// whether a wall touches it.
void ThermalModel::find_components() {
  const std::size_t n = p_.size();
  std::vector<std::size_t> root(n);
  std::iota(root.begin(), root.end(), std::size_t{0});
  auto find = [&](std::size_t i) {
    while (root[i] != i) i = root[i] = root[root[i]];
    return i;
  };
  for (std::size_t e = 0; e < contacts_.size(); ++e) {
    const Contact& k = contacts_[e];
    if (!(g_[e] > 0) || !p_.alive[k.i] || !p_.alive[k.j]) continue;
    const std::size_t a = find(k.i), b = find(k.j);
    if (a != b) root[std::max(a, b)] = std::min(a, b);
  }
  component_.assign(n, kNoComponent);
  component_size_.assign(n, 0);
  component_walled_.assign(n, 0);
  visited_.assign(n, 0);
  cluster_of_root_.assign(n, -1);
  for (std::size_t i = 0; i < n; ++i) {
    if (!p_.alive[i]) continue;
    const std::size_t r = find(i);
    component_[i] = static_cast<std::uint32_t>(r);
    ++component_size_[r];
    component_walled_[r] |= walls_.conductance[i] > 0;
  }
}

// A mark for a new walk over the particles (visited_ holds older ones).
std::uint32_t ThermalModel::next_stamp() {
  visited_.resize(p_.size(), 0);
  if (stamp_ == std::numeric_limits<std::uint32_t>::max()) {  // the stamps wrap: start again
    std::fill(visited_.begin(), visited_.end(), 0);
    stamp_ = 0;
  }
  return ++stamp_;
}

// The live particles joined to `from` by conducting contacts, `from` included, marked in
// visited_ with `stamp` (a breadth-first walk over L's pattern; without a conducting contact,
// `from` alone).
void ThermalModel::collect_component(Eigen::Index from, std::uint32_t stamp,
                                     std::vector<Eigen::Index>& out) {
  const SparseMatrix& m = all_.laplacian;
  std::size_t next = out.size();
  visited_[from] = stamp;
  out.push_back(from);
  if (!all_.has_conduction) return;  // no matrix: every particle is its own component
  for (; next < out.size(); ++next) {
    const Eigen::Index j = out[next];
    for (Eigen::Index k = m.outerIndexPtr()[j]; k < m.outerIndexPtr()[j + 1]; ++k) {
      const Eigen::Index r = m.innerIndexPtr()[k];
      if (visited_[r] == stamp || !p_.alive[r] ||
          !(contact_values_[static_cast<std::size_t>(k)] < 0))
        continue;
      visited_[r] = stamp;
      out.push_back(r);
    }
  }
}

// After a change of live set, the components of the touched particles (those whose flag
// changed and their neighbours), walked anew. Nothing else changes: a component that lost
// particles falls into pieces that each hold a neighbour of a lost one, and one that gained a
// particle holds that particle.
void ThermalModel::update_components(const std::vector<Eigen::Index>& touched) {
  const std::uint32_t stamp = next_stamp();
  std::vector<Eigen::Index> members;
  for (Eigen::Index i : touched) {
    if (!p_.alive[i]) component_[i] = kNoComponent;
    if (!p_.alive[i] || visited_[i] == stamp) continue;
    members.clear();
    collect_component(i, stamp, members);
    const Eigen::Index r = *std::min_element(members.begin(), members.end());
    std::uint8_t walled = 0;
    for (Eigen::Index j : members) {
      component_[j] = static_cast<std::uint32_t>(r);
      walled |= walls_.conductance[j] > 0;
    }
    component_size_[r] = static_cast<std::uint32_t>(members.size());
    component_walled_[r] = walled;
  }
}

std::uint32_t ThermalModel::component_of(std::size_t i) {
  check_particle_count("component_of");
  if (i >= p_.size())
    throw InputError("component_of: particle " + std::to_string(i) + " of " +
                     std::to_string(p_.size()));
  assemble_if_needed();
  if (!p_.alive[i]) throw RunError("component_of: particle " + std::to_string(i) + " is not live");
  return static_cast<std::uint32_t>(root_of(static_cast<Eigen::Index>(i)));
}

bool ThermalModel::in_insulated_cluster(std::size_t i) {
  const std::uint32_t r = component_of(i);
  return all_.has_conduction && insulated(r);
}

// The component named r is an insulated cluster: >= 2 particles, no wall touching it.
bool ThermalModel::insulated(std::uint32_t r) const {
  return clustered(r) && !component_walled_[r];
}

// The component named r is a cluster: >= 2 particles joined by conducting contacts.
bool ThermalModel::clustered(std::uint32_t r) const {
  return r != kNoComponent && component_size_[r] >= 2;
}

// A system's clusters (>= 2 live particles joined by conducting contacts, touching a wall or not):
// cluster id per row and the row grounded in each, the component's lowest particle (rows ascend,
// so it is the cluster's first row). A wall of little conductance leaves a stiff cluster as
// nearly singular as an insulated one, so walls make no difference here.
void ThermalModel::mark_clusters(System& s) {
  const auto m = static_cast<Eigen::Index>(s.rows());
  s.cluster.assign(static_cast<std::size_t>(m), -1);
  s.ground.clear();
  if (!s.has_conduction) return;
  for (Eigen::Index k = 0; k < m; ++k) {
    const std::size_t i =
        s.particle.empty() ? static_cast<std::size_t>(k) : static_cast<std::size_t>(s.particle[k]);
    const std::uint32_t r = component_[i];
    if (!clustered(r)) continue;
    if (r == i) {
      cluster_of_root_[r] = static_cast<int>(s.ground.size());
      s.ground.push_back(k);
    }
    s.cluster[k] = cluster_of_root_[r];
  }
}

// skip_resting: a live particle is busy when it received heat, differs in temperature from its
// component's lowest particle, or its walls' heat flow is not exactly zero; a component is busy
// when one of its particles is. The exact solution for a component at rest is theta^{n+1} =
// theta^n (L 1 = 0 and no source), so only the busy ones are solved, while they are under 3/4
// of the live particles; the others keep their temperatures exactly. True when this step
// solves busy_.
bool ThermalModel::select_busy(const Eigen::Ref<const Eigen::VectorXd>& theta0, const Heat& heat,
                               std::size_t live) {
  if (!spec_.skip_resting) return false;
  std::vector<Eigen::Index> rows =
      restless_known_ ? busy_rows_of_restless(theta0, heat) : busy_rows_of_all(theta0, heat);
  if (4 * rows.size() >= 3 * live) return false;
  if (rows != busy_.particle || busy_assembly_ != assembly_) build_busy_system(std::move(rows));
  return true;
}

namespace {
bool particle_busy(double dh, double theta, double theta_root, double wall_g, double wall_source) {
  return dh != 0 || theta != theta_root || wall_g * theta != wall_source;
}
}  // namespace

// Every live particle looked at (the first step, or when restless_ is not known).
std::vector<Eigen::Index> ThermalModel::busy_rows_of_all(
    const Eigen::Ref<const Eigen::VectorXd>& theta0, const Heat& heat) const {
  const auto n = static_cast<Eigen::Index>(p_.size());
  std::vector<std::uint8_t> busy(p_.size(), 0);  // by component
  for (Eigen::Index i = 0; i < n; ++i) {
    if (!p_.alive[i]) continue;
    const Eigen::Index r = root_of(i);
    if (particle_busy(heat.at(i), theta0[i], theta0[r], walls_.conductance[i], walls_.source[i]))
      busy[r] = 1;
  }
  std::vector<Eigen::Index> rows;
  for (Eigen::Index i = 0; i < n; ++i)
    if (p_.alive[i] && busy[root_of(i)]) rows.push_back(i);
  return rows;
}

// Only the components of restless_ and of the particles given heat: the others are at rest.
std::vector<Eigen::Index> ThermalModel::busy_rows_of_restless(
    const Eigen::Ref<const Eigen::VectorXd>& theta0, const Heat& heat) {
  if (busy_assembly_ == assembly_ && restless_ == busy_.particle)
    return busy_rows_kept_and_new(theta0, heat);
  std::vector<Eigen::Index> seeds = restless_;
  for (std::uint32_t i : heat.particles)
    if (heat.at(i) != 0) seeds.push_back(i);
  const std::uint32_t stamp = next_stamp();
  std::vector<Eigen::Index> rows, members;
  for (Eigen::Index i : seeds) {
    if (!p_.alive[i] || visited_[i] == stamp) continue;
    members.clear();
    collect_component(i, stamp, members);
    const Eigen::Index r = root_of(i);
    const bool busy = std::any_of(members.begin(), members.end(), [&](Eigen::Index j) {
      return particle_busy(heat.at(j), theta0[j], theta0[r], walls_.conductance[j],
                           walls_.source[j]);
    });
    if (busy) rows.insert(rows.end(), members.begin(), members.end());
  }
  std::sort(rows.begin(), rows.end());
  return rows;
}

// busy_rows_of_restless when restless_ is busy_'s rows, whole components of this assembly in
// ascending order (the common case: one sub-step, no vaporisation): those still busy are kept
// in their order, without walking them, and the components of heated particles outside them
// are walked and merged in. The same rows as the walk from every seed (10^6 spheres, 10^5 rays,
// K = 100, the paper's step, one pulse: heat 31.0 s with the walk, 22.7 s without).
std::vector<Eigen::Index> ThermalModel::busy_rows_kept_and_new(
    const Eigen::Ref<const Eigen::VectorXd>& theta0, const Heat& heat) {
  // Stamps on the roots of busy_'s components: at rest, or busy; then on new components' members.
  const std::uint32_t at_rest = next_stamp(), busy = next_stamp(), walked = next_stamp();
  for (Eigen::Index i : busy_.particle) {
    const Eigen::Index r = root_of(i);
    if (visited_[r] != busy)
      visited_[r] =
          particle_busy(heat.at(i), theta0[i], theta0[r], walls_.conductance[i], walls_.source[i])
              ? busy
              : at_rest;
  }
  std::vector<Eigen::Index> kept, added;
  kept.reserve(busy_.particle.size());
  for (Eigen::Index i : busy_.particle)
    if (visited_[root_of(i)] == busy) kept.push_back(i);
  for (std::uint32_t i : heat.particles) {
    if (heat.at(i) == 0 || !p_.alive[i]) continue;
    const std::uint32_t mark = visited_[root_of(i)];
    if (mark == at_rest || mark == busy || mark == walked) continue;
    collect_component(i, walked, added);
  }
  if (added.empty()) return kept;
  std::sort(added.begin(), added.end());
  std::vector<Eigen::Index> rows(kept.size() + added.size());
  std::merge(kept.begin(), kept.end(), added.begin(), added.end(), rows.begin());
  return rows;
}

// busy_ cut from all_: the rows' columns of L + W (their nonzero entries stay inside the rows'
// components; explicit zeros of contacts with vaporised particles are dropped) and their clusters.
// Column k is particle rows[k]'s column (rows ascend, so its entries stay sorted), written straight
// into the compressed arrays with rows over threads: each column's count, their offsets, then the
// entries (the same matrix as inserted column by column, which on every change of the busy rows
// was 10% of a 10^6-sphere run's profile).
void ThermalModel::build_busy_system(std::vector<Eigen::Index> rows) {
  System& s = busy_;
  const auto m = static_cast<Eigen::Index>(rows.size());
  std::vector<Eigen::Index>& row_of = row_of_;  // -1 outside the rows between calls
  row_of.resize(p_.size(), -1);
  for_each_row(m, [&](Eigen::Index k) { row_of[rows[k]] = k; });
  s.diagonal.resize(m), s.wall_source.resize(m), s.wall_conductance.resize(m);
  s.has_conduction = all_.has_conduction;
  if (s.has_conduction) {
    const SparseMatrix& all = all_.laplacian;
    s.laplacian = SparseMatrix(m, m);
    int* outer = s.laplacian.outerIndexPtr();
    for_each_row(m, [&](Eigen::Index k) {
      int count = 0;
      for (SparseMatrix::InnerIterator it(all, rows[k]); it; ++it) count += row_of[it.row()] >= 0;
      outer[k + 1] = count;  // a vaporised neighbour's explicit zero is left out
    });
    for (Eigen::Index k = 0; k < m; ++k) outer[k + 1] += outer[k];
    s.laplacian.resizeNonZeros(outer[m]);
    s.diag_pos.resize(static_cast<std::size_t>(m));
    int* inner = s.laplacian.innerIndexPtr();
    double* values = s.laplacian.valuePtr();
    for_each_row(m, [&](Eigen::Index k) {
      Eigen::Index at = outer[k];
      for (SparseMatrix::InnerIterator it(all, rows[k]); it; ++it) {
        const Eigen::Index r = row_of[it.row()];
        if (r < 0) continue;
        if (r == k) s.diag_pos[k] = at, s.diagonal[k] = it.value();
        inner[at] = static_cast<int>(r), values[at] = it.value();
        ++at;
      }
    });
  } else {
    s.laplacian = SparseMatrix();
    for (Eigen::Index k = 0; k < m; ++k) s.diagonal[k] = all_.diagonal[rows[k]];  // the walls'
  }
  for_each_row(m, [&](Eigen::Index k) {
    s.wall_source[k] = all_.wall_source[rows[k]];
    s.wall_conductance[k] = all_.wall_conductance[rows[k]];
    row_of[rows[k]] = -1;
  });
  s.live.assign(static_cast<std::size_t>(m), 1);
  s.pattern_version = ++versions_;
  s.particle = std::move(rows);
  mark_clusters(s);
  busy_assembly_ = assembly_;
}

double ThermalModel::thermal_mass(std::size_t i) const {
  const Material& m = materials_[p_.material[i]];
  return m.density * p_.volume(i) * effective_heat_capacity(m, p_.temperature[i], 0) /
         spec_.time_scaling;
}

// c_i = m_i C_i / M (section 4.1). A dead particle's row reads c theta = c theta; its c is the
// mean live one so that it neither dominates nor vanishes from the relative residual of CG.
// Over the step's rows (every particle, or busy_'s, all live).
Eigen::VectorXd ThermalModel::thermal_masses() const {
  const Eigen::Index n = rows();
  Eigen::VectorXd c(n);
  double sum = 0;
  std::size_t live = 0;
  for (Eigen::Index k = 0; k < n; ++k) {
    const std::size_t i = particle_of(k);
    if (!p_.alive[i]) continue;
    c[k] = thermal_mass(i);
    BEAMPACK_DCHECK(c[k] > 0.0 && std::isfinite(c[k]), "particle %zu: thermal mass %g J/K at %g K",
                    i, c[k], p_.temperature[i]);
    sum += c[k];
    ++live;
  }
  const double filler = live ? sum / live : 1.0;
  for (Eigen::Index k = 0; k < n; ++k)
    if (!p_.alive[particle_of(k)]) c[k] = filler;
  return c;
}

Eigen::VectorXd ThermalModel::thermal_masses_with_bands(
    const Eigen::VectorXd& theta0, const std::vector<std::uint8_t>& bands) const {
  Eigen::VectorXd c = thermal_masses();
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    if (!p_.alive[i] || !bands[k]) continue;
    const Material& m = materials_[p_.material[i]];
    c[k] = m.density * p_.volume(i) * effective_heat_capacity(m, theta0[k], bands[k]) /
           spec_.time_scaling;
  }
  return c;
}

double ThermalModel::monotone_step_limit() const {
  check_particle_count("monotone_step_limit");
  if (spec_.phi >= 1.0) return std::numeric_limits<double>::infinity();
  const_cast<ThermalModel*>(this)->assemble_if_needed();
  if (limit_assembly_ == assembly_) return limit_;  // same live set and matrix: same limit
  // With the smaller of C_S and C_L: a particle that melts in an early sub-step must not make the
  // later ones exceed the limit (a material with C_L < C_S).
  double limit = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < p_.size(); ++i) {
    const double d = all_.diagonal[static_cast<Eigen::Index>(i)];
    if (!p_.alive[i] || !(d > 0)) continue;
    const double c =
        least_thermal_mass(materials_[p_.material[i]], p_.volume(i), spec_.time_scaling);
    limit = std::min(limit, c / ((1.0 - spec_.phi) * d));
  }
  limit_ = limit, limit_assembly_ = assembly_;
  return limit;
}

// Bound on the iteration matrix of (3.11), || dt phi c^{-1} (L + W) ||_inf (Gershgorin).
double ThermalModel::contraction_estimate(const System& s, double dt,
                                          const Eigen::VectorXd& c) const {
  double worst = 0;
  for (Eigen::Index k = 0; k < c.size(); ++k)
    if (s.live[k]) worst = std::max(worst, (2.0 * s.diagonal[k] - s.wall_conductance[k]) / c[k]);
  return dt * spec_.phi * worst;
}

// Solves (3.10) for theta1 given the capacities c:
//   (c + dt phi (L + W)) theta1 = c theta0 + dt (1 - phi) Q(theta0) + dt phi b + dH,
// Q(theta) = b - (L + W) theta, b the wall sources. Without a conducting contact the system is
// diagonal and no matrix is built. Solved for t.rel1 from t.rel0 (relative to reference_, which
// moves b only; the iterative solvers start from t.rel1); t.theta1 follows. With busy_ only its
// rows are solved; the others are at rest.
void ThermalModel::solve(double dt, const Eigen::VectorXd& c, const Eigen::VectorXd& dh,
                         StepTemperatures& t, StepReport& report) {
  if (!solve_busy_ && clusters_assembly_ != assembly_) {  // the whole system's, when it is solved
    mark_clusters(all_);
    clusters_assembly_ = assembly_;
  }
  if (rows() > 0) solve_relative(solve_busy_ ? busy_ : all_, dt, c, t.rel0, dh, t.rel1, report);
  // theta0 plus the change, not rel1 + reference_: the round trip through the reference loses a
  // bit where theta - reference has another exponent than theta, and could take a heated
  // particle below its start. The change is >= 0 wherever the solve's is (rounding is monotone).
  t.theta1 = t.theta0 + (t.rel1 - t.rel0);
}

void ThermalModel::solve_relative(const System& s, double dt, const Eigen::VectorXd& c,
                                  const Eigen::VectorXd& theta0, const Eigen::VectorXd& dh,
                                  Eigen::VectorXd& theta1, StepReport& report) {
  const double implicit = dt * spec_.phi, explicit_part = dt * (1.0 - spec_.phi);
  const Eigen::VectorXd flux_in =
      s.has_conduction ? symmetric_product(s.laplacian, theta0) : s.diagonal.cwiseProduct(theta0);
  const Eigen::VectorXd drive = dt * (s.wall_source - flux_in) + dh;
  ++report.solves;
  if (!s.has_conduction ||
      spec_.phi == 0) {  // the change, so heating never rounds theta below theta0
    theta1 = theta0 + drive.cwiseQuotient(c + implicit * s.diagonal);
    report.solver = s.has_conduction ? "explicit" : has_walls_ ? "diagonal" : "none";
    report.conduction_ran = s.has_conduction;
    return;
  }
  SparseMatrix& a = step_matrix(s, implicit, c);
  const double rho = contraction_estimate(s, dt, c);
  report.contraction_estimate = std::max(report.contraction_estimate, rho);
  report.conduction_ran = true;
  report.solver =
      spec_.solver == "auto" ? auto_solver(rho, a.rows(), spec_.max_iterations) : spec_.solver;
  // A cluster's rows summed: (c + dt phi W)^T theta1 = its energy (the contacts' terms cancel).
  const Eigen::VectorXd weight = c + implicit * s.wall_conductance;
  if (report.solver != "direct" && solve_change(a, c, drive, rho, theta0, theta1, report)) {
    const Eigen::VectorXd own = dt * (s.wall_source - s.wall_conductance.cwiseProduct(theta0)) + dh;
    keep_energy_of_components(s, weight, own, theta0, theta1);
    return;
  }
  // The factorisation solves for theta1 itself: at a stiff step dt (L + W) theta0 is far larger
  // than the change, and its rounding would enter the clusters' energy balance.
  const Eigen::VectorXd rhs = c.cwiseProduct(theta0) + explicit_part * (s.wall_source - flux_in) +
                              implicit * s.wall_source + dh;
  solve_direct_grounded(s, a, weight, rhs, theta1, report);
}

// A = c + dt phi (L + W) over s's rows. The matrix is kept between steps: its pattern is copied
// when s's changes, and its values are written in place (making a new one every step took 19% of
// a profile of the DEM bed's heat steps at the paper's dt). The same values as
// implicit * s.laplacian plus c on the diagonal.
SparseMatrix& ThermalModel::step_matrix(const System& s, double implicit,
                                        const Eigen::VectorXd& c) {
  if (step_matrix_version_ != s.pattern_version || step_matrix_.rows() != s.laplacian.rows() ||
      step_matrix_.nonZeros() != s.laplacian.nonZeros()) {
    step_matrix_ = s.laplacian;
    step_matrix_version_ = s.pattern_version;
  }
  const double* l = s.laplacian.valuePtr();
  double* v = step_matrix_.valuePtr();
  for (Eigen::Index k = 0; k < s.laplacian.nonZeros(); ++k) v[k] = implicit * l[k];
  for (Eigen::Index i = 0; i < c.size(); ++i) v[s.diag_pos[i]] += c[i];
  return step_matrix_;
}

// An iterative solve stops at a residual relative to its drive, dt Q(theta0) + dH. At a stiff step
// that drive is far larger than what the step changes (dt L theta0 >> c (theta1 - theta0)), and
// the residual left lies mostly along each cluster's constant vector: its energy. Summed over a
// component, the step (3.10) reads
//   (c + dt phi W)^T (theta1 - theta0) = sum(dt (b - W theta0) + dH),
// `own` per row (1^T L = 0: the contacts only move heat within it). A uniform shift of each
// cluster's change restores that balance exactly, and keeps the solver's accuracy within it; a
// lone particle's row is decoupled, and is solved exactly.
void ThermalModel::keep_energy_of_components(const System& s, const Eigen::VectorXd& weight,
                                             const Eigen::VectorXd& own,
                                             const Eigen::VectorXd& theta0,
                                             Eigen::VectorXd& theta1) const {
  const std::size_t clusters = s.ground.size();
  std::vector<double> energy(clusters, 0.0), held(clusters, 0.0), mass(clusters, 0.0);
  for (Eigen::Index i = 0; i < theta1.size(); ++i) {
    const int k = s.cluster[i];
    if (k < 0) {
      theta1[i] = theta0[i] + own[i] / weight[i];
      continue;
    }
    energy[k] += own[i];
    held[k] += weight[i] * (theta1[i] - theta0[i]);
    mass[k] += weight[i];
  }
  for (Eigen::Index i = 0; i < theta1.size(); ++i) {
    const int k = s.cluster[i];
    if (k >= 0) theta1[i] += (energy[k] - held[k]) / mass[k];
  }
}

// The iterative solvers solve for the step's change, A (theta1 - theta0) = dt Q(theta0) + dH (the
// drive), so that their tolerances measure what the step changes. Against the temperatures
// themselves (from 0 K without walls) a deposit below tolerance * c theta stopped CG before its
// first iteration, and the step lost that heat. False when an iterative solve failed under
// "auto": the caller then factorises (auto promised a stable answer).
bool ThermalModel::solve_change(const SparseMatrix& a, const Eigen::VectorXd& c,
                                const Eigen::VectorXd& drive, double rho,
                                const Eigen::VectorXd& theta0, Eigen::VectorXd& theta1,
                                StepReport& report) const {
  Eigen::VectorXd change = theta1 - theta0;  // the first guess: 0, or the corrector's last pass
  // A last pass whose capacities were orders of magnitude below this pass's (c_solid = 1e-14 and
  // a latent band) left a change of 1e18 K; the first update cancelled it to exactly 0 and the
  // fixed-point iteration read that as divergence. A guess worse than none is not taken.
  if (!change.isZero(0.0) && (drive - a * change).squaredNorm() > drive.squaredNorm())
    change.setZero();
  SolveStats stats;
  try {
    stats = report.solver == "fixed-point"
                ? fixed_point_solve(a, c, drive, change, spec_.tolerance, spec_.max_iterations, rho)
                : cg_solve(a, drive, change, spec_.tolerance, spec_.max_iterations);
  } catch (const SolverRefusal&) {  // a defect (non-finite inputs) is no case for the fallback
    if (spec_.solver != "auto") throw;
    report.solver = "direct";
    return false;
  }
  theta1 = theta0 + change;
  report.iterations += stats.iterations;
  return true;
}

// Stiff steps (dt phi G >> c, e.g. K = 1e9 or a long cooling step): on a cluster that is
// insulated, or touches walls of little conductance, A = C + dt phi (L + W) is nearly singular:
// its constant vector has eigenvalue ~ c, next to others ~ dt phi G up to 1e18 times larger. A
// factorisation of A then loses the cluster's mean temperature, i.e. its energy (heat appeared,
// the maximum principle broke by kelvins), and meets zero pivots. Grounding one particle r per
// cluster, A' = A + a_rr e_r e_r^T, makes the matrix as well conditioned as the contact graph.
// The exact solution is theta = y + alpha u with A' y = rhs and A' u = e_r: every row but r holds
// for any alpha, and row r holds exactly when the cluster's energy balance does,
// 1^T A theta = w^T theta = 1^T rhs, with w = c + dt phi W (1^T L = 0 over a cluster). That fixes
// alpha = (1^T rhs - w^T y) / w^T u: Sherman-Morrison with its ill-conditioned scalar replaced by
// the conservation law. One factorisation, two solves (all clusters at once).
void ThermalModel::solve_direct_grounded(const System& s, SparseMatrix& a, const Eigen::VectorXd& w,
                                         const Eigen::VectorXd& rhs, Eigen::VectorXd& theta1,
                                         StepReport& report) {
  auto first_solve = [&](Eigen::VectorXd& x) {
    direct_.solve(a, s.pattern_version, rhs, x);
    report.symbolic_reused = direct_.symbolic_reused();
    report.factors_reused = direct_.factors_reused();
  };
  if (s.ground.empty()) return first_solve(theta1);
  Eigen::VectorXd e_r = Eigen::VectorXd::Zero(rhs.size());
  for (Eigen::Index r : s.ground) {
    a.valuePtr()[s.diag_pos[r]] *= 2.0;
    e_r[r] = 1.0;
  }
  Eigen::VectorXd y, u;
  first_solve(y);
  direct_.solve(a, s.pattern_version, e_r, u);  // same values: the factors are reused
  const std::size_t clusters = s.ground.size();
  std::vector<double> energy(clusters, 0.0), wy(clusters, 0.0), wu(clusters, 0.0);
  for (Eigen::Index i = 0; i < rhs.size(); ++i) {
    const int k = s.cluster[i];
    if (k < 0) continue;
    energy[k] += rhs[i];
    wy[k] += w[i] * y[i];
    wu[k] += w[i] * u[i];
  }
  theta1 = y;
  for (Eigen::Index i = 0; i < rhs.size(); ++i) {
    const int k = s.cluster[i];
    if (k >= 0) theta1[i] += (energy[k] - wy[k]) / wu[k] * u[i];
  }
  if (!theta1.allFinite()) throw RunError("thermal direct solver: non-finite temperature");
}

// Phase work is needed only where some particle is at or above theta_m before or after the
// predictor; otherwise no band can be crossed (theta_m < theta_v).
bool ThermalModel::phase_work_needed(const Eigen::VectorXd& theta0,
                                     const Eigen::VectorXd& theta1) const {
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    if (!p_.alive[i]) continue;
    const double melt = materials_[p_.material[i]].melt_temperature;
    if (theta0[k] >= melt || theta1[k] >= melt) return true;
  }
  return false;
}

// Paper, section 4 (predictor-corrector, (4.2)): a particle whose predicted step crosses theta_m
// or theta_v is re-solved with C_eff = C + delta P / delta theta for every band crossed. Bands are
// kept once crossed within the step so the passes cannot cycle; passes stop when no new band
// appears (or at thermal.max_phase_corrections).
void ThermalModel::correct_phases(double dt, const Eigen::VectorXd& dh, Eigen::VectorXd& c,
                                  StepTemperatures& t, StepReport& report) {
  const Eigen::VectorXd& theta0 = t.theta0;
  const Eigen::VectorXd& theta1 = t.theta1;
  std::vector<std::uint8_t> bands(static_cast<std::size_t>(rows()), 0);
  int passes = 0;
  for (;;) {
    bool grew = false;
    for (Eigen::Index k = 0; k < rows(); ++k) {
      const std::size_t i = particle_of(k);
      if (!p_.alive[i]) continue;
      const std::uint8_t b = crossed_bands(materials_[p_.material[i]], theta0[k], theta1[k]);
      if (b & ~bands[k]) {
        bands[k] |= b;
        grew = true;
      }
    }
    if (!grew) break;
    if (passes == spec_.max_phase_corrections) {
      report.phase_passes_capped = true;
      break;
    }
    c = thermal_masses_with_bands(theta0, bands);
    solve(dt, c, dh, t, report);
    report.phase_corrected = true;
    ++passes;
  }
  if (passes > 0) count_bands_short(theta0, theta1, bands, report);
}

void ThermalModel::count_bands_short(const Eigen::VectorXd& theta0, const Eigen::VectorXd& theta1,
                                     const std::vector<std::uint8_t>& bands,
                                     StepReport& report) const {
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    if (!bands[k] || !p_.alive[i]) continue;
    const Material& m = materials_[p_.material[i]];
    const std::uint8_t short_of = bands[k] & ~crossed_bands(m, theta0[k], theta1[k]);
    if (!short_of) continue;
    const double band =
        effective_heat_capacity(m, theta0[k], short_of) - effective_heat_capacity(m, theta0[k], 0);
    if (band == 0) continue;  // a band of no latent heat charged nothing
    ++report.bands_short;
    report.band_heat_short +=
        m.density * p_.volume(i) * band / spec_.time_scaling * std::abs(theta1[k] - theta0[k]);
  }
}

// The ledger: stored gains the M-scaled (m C_eff / M) dtheta each particle keeps, so
// absorbed = stored + vaporized + walls holds to the solver tolerance, and to the rounding of
// rises into temperatures (a rise below ~1e-16 of a temperature is lost to it, and shows).
void ThermalModel::account(double dt, const Eigen::VectorXd& c, const StepTemperatures& t,
                           const Eigen::VectorXd& dh) {
  const Eigen::VectorXd& theta0 = t.rel0;
  const Eigen::VectorXd& theta1 = t.rel1;
  double stored = 0, walls = 0;
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    if (!p_.alive[i]) continue;
    remember(i);
    // The change the particle keeps: a rise below the last digit of its temperature is lost to
    // it, and the ledger says so (the relative one keeps digits the temperature cannot).
    const double de = c[k] * (t.theta1[k] - t.theta0[k]);
    stored_[i] += de;
    stored += de;
    const double mean = spec_.phi * theta1[k] + (1.0 - spec_.phi) * theta0[k];
    walls += dt * (walls_.conductance[i] * mean - all_.wall_source[static_cast<Eigen::Index>(i)]);
  }
  ledger_.absorbed += dh.sum();
  ledger_.stored += stored;
  ledger_.walls += walls;
}

// A particle at or above theta_v is vaporised: it leaves the particles, the graph and the masses,
// taking its stored energy with it; at or above theta_m it is liquid (C_L, liquid index).
void ThermalModel::update_phases(const Eigen::VectorXd& theta1, StepReport& report) {
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    if (!p_.alive[i]) continue;
    remember(i);
    p_.temperature[i] = theta1[k];
    const Phase phase = phase_at(materials_[p_.material[i]], theta1[k]);
    if (phase != Phase::vapor) {
      p_.phase[i] = phase;
      continue;
    }
    p_.remove(i);
    if (i < contact_degree_.size() && removed_contacts_bound_ != kBoundUnknown)
      removed_contacts_bound_ += contact_degree_[i];
    flipped_.push_back(static_cast<Eigen::Index>(i));
    ledger_.vaporized += stored_[i];
    ledger_.stored -= stored_[i];
    stored_[i] = 0;
    report.vaporized.push_back(static_cast<std::uint32_t>(i));
    dirty_ = true;
  }
}

// Energy aimed at a particle that vaporised in an earlier sub-step leaves with the vapour.
void ThermalModel::book_heat_of_vaporised(const Heat& heat) {
  for (std::uint32_t i : heat.particles) {
    const double e = heat.at(i);
    if (p_.alive[i] || e == 0) continue;
    ledger_.absorbed += e;
    ledger_.vaporized += e;
  }
}

// The heat of the step's rows (none for a particle no longer live).
Eigen::VectorXd ThermalModel::heat_of_rows(const Heat& heat) const {
  Eigen::VectorXd dh(rows());
  for (Eigen::Index k = 0; k < rows(); ++k) {
    const std::size_t i = particle_of(k);
    dh[k] = p_.alive[i] ? heat.at(i) : 0.0;
  }
  return dh;
}

StepReport ThermalModel::step_once(double dt, const Heat& heat) {
  StepReport report;
  assemble_if_needed();
  book_heat_of_vaporised(heat);
  const Eigen::Map<const Eigen::VectorXd> theta(p_.temperature.data(),
                                                static_cast<Eigen::Index>(p_.size()));
  report.live_rows = live_count_;
  solve_busy_ = select_busy(theta, heat, report.live_rows);
  report.solved_rows = solve_busy_ ? busy_.particle.size() : report.live_rows;
  // From here on the step works on its rows: every particle, or the busy components' only (the
  // others keep their temperatures, phases and ledger entries exactly).
  StepTemperatures t;
  t.theta0 = solve_busy_ ? Eigen::VectorXd(theta(busy_.particle)) : Eigen::VectorXd(theta);
  const Eigen::VectorXd dh = heat_of_rows(heat);
  t.rel0 = t.theta0.array() - reference_;
  t.rel1 = t.rel0;  // the iterative solvers' first guess: no change
  Eigen::VectorXd c = thermal_masses();
  solve(dt, c, dh, t, report);  // predictor
  report.phases_ran = phase_work_needed(t.theta0, t.theta1);
  if (report.phases_ran)
    report.phases_seconds += seconds_of([&] { correct_phases(dt, dh, c, t, report); });
  account(dt, c, t, dh);
  const double update = seconds_of([&] { update_phases(t.theta1, report); });
  // Below theta_m everywhere the phase update is a scan that finds nothing: heat's time.
  if (report.phases_ran) report.phases_seconds += update;
  return report;
}

StepReport ThermalModel::step(double dt, const std::vector<double>& absorbed) {
  std::vector<std::uint32_t> given;
  for (std::size_t i = 0; i < absorbed.size(); ++i)
    if (absorbed[i] != 0) given.push_back(static_cast<std::uint32_t>(i));
  return step(dt, absorbed, given);
}

StepReport ThermalModel::step(double dt, const std::vector<double>& absorbed,
                              std::span<const std::uint32_t> given) {
  check_particle_count("step");
  undo_ready_ = false;  // a step refused below leaves nothing to undo
  if (!(std::isfinite(dt) && dt > 0)) input_error("thermal.dt", dt, "must be > 0");
  Heat heat = checked_heat(absorbed, given);
  const int substeps = substep_count(dt);
  heat.parts = substeps;
  begin_undo();
  StepReport report;
  std::vector<Eigen::Index> solved;  // rows of every sub-step: the next step's restless_
  bool whole = false;
  try {
    for (int k = 0; k < substeps; ++k) {
      add_substep(report, step_once(dt / substeps, heat));
      if (solve_busy_) {
        solved.insert(solved.end(), busy_.particle.begin(), busy_.particle.end());
        restless_ = busy_.particle, restless_known_ = true;  // for the next sub-step
      } else {  // a whole solve may move resting components by rounding: look at every particle
        whole = true;
        restless_known_ = false;
      }
    }
  } catch (...) {  // a solver that failed (diverged, stagnated): the step changes nothing
    put_back_changed();
    restless_known_ = false;
    undo_ready_ = false;
    throw;
  }
  report.substeps = substeps;
  if (substeps > 1) {  // one sub-step's rows are busy_'s: ascending already
    std::sort(solved.begin(), solved.end());
    solved.erase(std::unique(solved.begin(), solved.end()), solved.end());
  }
  restless_ = std::move(solved);
  restless_known_ = !whole;
  serial_before_step_ = serial_;
  serial_ = new_serial();
  for (const Undo& u : undo_)  // every particle whose phase the step set is in undo_
    if (p_.alive[u.particle] && p_.phase[u.particle] != u.phase)
      report.phase_changed.push_back(static_cast<std::uint32_t>(u.particle));
  std::sort(report.phase_changed.begin(), report.phase_changed.end());
  return report;
}

// The deposits as the step reads them: `given` (any order, repeats allowed) lists every particle
// whose absorbed energy is not zero; each must be finite, >= 0 and into a live particle.
ThermalModel::Heat ThermalModel::checked_heat(const std::vector<double>& absorbed,
                                              std::span<const std::uint32_t> given) const {
  const std::size_t n = p_.size();
  if (!absorbed.empty() && absorbed.size() != n)
    throw InputError("thermal step: " + std::to_string(absorbed.size()) +
                     " absorbed energies for " + std::to_string(n) + " particles");
  Heat heat{&absorbed, std::vector<std::uint32_t>(given.begin(), given.end()), 1};
  std::sort(heat.particles.begin(), heat.particles.end());  // sums in particle order
  heat.particles.erase(std::unique(heat.particles.begin(), heat.particles.end()),
                       heat.particles.end());
  for (std::uint32_t i : heat.particles) {
    if (i >= absorbed.size())
      throw InputError("thermal step: heated particle " + std::to_string(i) +
                       " has no absorbed energy");
    if (!(std::isfinite(absorbed[i]) && absorbed[i] >= 0))
      throw InputError("thermal step: absorbed energy of particle " + std::to_string(i) + " = " +
                       shown_number(absorbed[i]) + " J: must be finite and >= 0");
    if (!p_.alive[i] && absorbed[i] > 0)
      throw RunError("thermal step: energy deposited into vaporised particle " + std::to_string(i) +
                     " (the ray scene was not updated after its removal)");
  }
  return heat;
}

// phi < 1 is monotone (and for phi < 1/2 stable) only below its step limit: split, or refuse.
int ThermalModel::substep_count(double dt) const {
  const double limit = monotone_step_limit();
  const double parts = dt > limit ? std::ceil(dt / limit) : 1.0;
  if (parts > spec_.max_substeps) {
    std::ostringstream msg;
    msg << "a step of " << dt << " s with thermal.phi = " << spec_.phi << " exceeds the "
        << (spec_.phi < 0.5 ? "explicit stability limit " : "limit for a monotone step ") << limit
        << " s (min_i m_i C_i / (M (1 - phi) (sum_j G_ij + W_i)), C_i the lesser of C_S and C_L, "
           "W_i the walls' conductance) and would need "
        << parts << " sub-steps > thermal.max_substeps = " << spec_.max_substeps
        << ": use thermal.phi = 1 (monotone at any step) or a smaller thermal.dt";
    throw InputError(msg.str());
  }
  return static_cast<int>(parts);
}

// undo_step's record starts empty for each step.
void ThermalModel::begin_undo() {
  clear_undo();
  undo_ledger_ = ledger_;
  undo_ready_ = true;
}

void ThermalModel::clear_undo() {
  for (const Undo& u : undo_) undo_slot_[u.particle] = -1;
  undo_.clear();
  undo_slot_.resize(p_.size(), -1);
  undo_ready_ = false;
}

void ThermalModel::add_substep(StepReport& report, const StepReport& sub) {
  report.vaporized.insert(report.vaporized.end(), sub.vaporized.begin(), sub.vaporized.end());
  report.solver = sub.solver;
  report.iterations += sub.iterations;
  report.solves += sub.solves;
  report.contraction_estimate = std::max(report.contraction_estimate, sub.contraction_estimate);
  report.conduction_ran |= sub.conduction_ran;
  report.solved_rows += sub.solved_rows;
  report.live_rows += sub.live_rows;
  report.phases_ran |= sub.phases_ran;
  report.phases_seconds += sub.phases_seconds;
  report.phase_corrected |= sub.phase_corrected;
  report.phase_passes_capped |= sub.phase_passes_capped;
  report.bands_short += sub.bands_short;
  report.band_heat_short += sub.band_heat_short;
  report.symbolic_reused = sub.symbolic_reused;
  report.factors_reused = sub.factors_reused;
}

// Particle i's state before the step's first change to it.
void ThermalModel::remember(std::size_t i) {
  if (undo_slot_[i] >= 0) return;
  undo_slot_[i] = static_cast<std::int32_t>(undo_.size());
  undo_.push_back({i, p_.temperature[i], stored_[i], p_.phase[i], p_.alive[i]});
}

void ThermalModel::undo_step() {
  check_particle_count("undo_step");
  if (!undo_ready_) throw RunError("thermal undo_step: no step to undo (once per step)");
  put_back_changed();
  serial_ = serial_before_step_;  // that state again; restless_ (the step's rows) holds for it
  undo_ready_ = false;
}

// The particles the step changed, and the ledger, as they were before it.
void ThermalModel::put_back_changed() {
  for (const Undo& u : undo_) {
    const std::size_t i = u.particle;
    p_.temperature[i] = u.temperature;
    p_.phase[i] = u.phase;
    stored_[i] = u.stored;
    if (p_.alive[i] != u.alive)
      p_.alive[i] = u.alive, dirty_ = true, flipped_.push_back(static_cast<Eigen::Index>(i));
  }
  ledger_ = undo_ledger_;
}

Phase ThermalModel::phase_before_step(std::size_t i) const {
  const std::int32_t slot = i < undo_slot_.size() ? undo_slot_[i] : -1;
  return slot >= 0 ? undo_[static_cast<std::size_t>(slot)].phase : p_.phase[i];
}

ThermalModel::Snapshot ThermalModel::save() const {
  check_particle_count("save");
  return {p_.temperature, p_.phase, p_.alive, stored_, ledger_, serial_, reference_};
}

void ThermalModel::restore(const Snapshot& s) {
  check_particle_count("restore");
  // Every array, or a short one would leave the particles' arrays of different lengths.
  for (const std::size_t n : {s.temperature.size(), s.phase.size(), s.alive.size()})
    if (n != p_.size())
      throw RunError("thermal restore: snapshot of " + std::to_string(n) +
                     " particles, model has " + std::to_string(p_.size()));
  // Reassemble only if the live set differs from the matrix's: a redo without vaporisation keeps
  // it (compared with the assembled set, not p_.alive, which a checkpoint may have set already).
  if (all_.live != s.alive) dirty_ = true;
  removed_contacts_bound_ = kBoundUnknown;  // any live set: drop_removed_contacts counts anew
  // Without walls the reference moves no term of the system (no wall sources): it is taken over.
  // With walls it is the first wall's temperature, as the spec gives it.
  if (!has_walls_) {
    if (!std::isfinite(s.reference))
      throw RunError("thermal restore: reference temperature " + std::to_string(s.reference));
    reference_ = s.reference;
  }
  // restless_ holds every component not at rest in the state now and in the state before the
  // last step (if it solved no sub-step whole): any other state is looked at whole.
  flips_known_ = false;  // any live flag may change below
  const bool known_state =
      s.serial != 0 && (s.serial == serial_ || s.serial == serial_before_step_);
  if (!known_state) restless_known_ = false;
  serial_ = known_state ? s.serial : new_serial();
  clear_undo();  // nothing to undo: the last step's record no longer describes this state
  p_.temperature = s.temperature;
  p_.phase = s.phase;
  p_.alive = s.alive;
  stored_ = s.stored;
  ledger_ = s.ledger;
}

}  // namespace beampack
