// `beampack validate --stiff`: a grid over conductivity, time step, index, particle count, phi,
// solver and scene (the beam on a cold bed, or on a liquid bed cooled by walls). Each cell either
// runs, stays bounded, closes its ledgers, conducts as its conductivity says and agrees with the
// other solvers of its group, or is refused for one of the reasons the grid expects; anything else
// (NaN, crash, unbounded temperature, another refusal) is a failure.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <string>
#include <vector>

#include "geometry/error.h"
#include "tools/run_command.h"
#include "tools/run_config.h"
#include "tools/stability.h"

namespace beampack::tools {
namespace {

// A step as long as the pulses' period: each pulse, then its cooling, in one step.
constexpr const char* kCoolingStep = "1e-9";

// The solvers of a group agree to this (K): thermal.tolerance (1e-10, relative) of temperatures
// up to 1e3 K is 1e-7 K per solve; ten times that. The worst disagreement measured over the grid
// is 4.6e-8 K; a fixed-point iteration stopped at 1e-6 instead of 1e-10 is off by 5.8e-6 K.
constexpr double kSolverAgreement = 1e-6;

// Heat that solid particles hold beyond what they absorbed (conducted_fraction): round-off where
// nothing conducts (K = 0 or one particle; at most 1.1e-12 measured, a metal's few joules summed
// over many hits), at least 7.2e-3 (measured) where particles with K > 0 touch.
constexpr double kNoConduction = 1e-10, kConducted = 1e-4;
// The heat ledger of the walls scene under an iterative solve: its change form sums wall terms
// dt W (theta - theta_w) as large as 1e6 times the heat a step stores (K = 1e6, a 1e-9 s step),
// whose round-off (1e-16 of them) leaves the ledger open by ~1e-10 (1.1e-10 measured with CG at
// 3000 particles, at any thermal.tolerance from 1e-8 to 1e-12; 2.2e-10 over the ledger's scale
// since a cooling bed's heat counts once); the factorisation, which solves for the temperatures
// themselves, closes it to 2.1e-12, the rounding of the rises into the temperatures the ledger
// books, and is held to 1e-10. Between four and five times the worst seen.
constexpr double kWallsHeatRoundOff = 1e-9;
// The vaporised fractions of two solvers that end in the same phases: the same sum, to round-off.
constexpr double kRoundOff = 1e-12;

struct Cell {
  std::string conductivity, dt, index, count, phi, solver;
  std::string scene = "beam";  // or "walls": kWallsScene
};

// The walls scene: the bed starts liquid at 650 K, between theta_m (600 K) and theta_v, and six
// walls at 300 K reach every particle; it cools through its solidification band (or, beside the
// beam, heats on). Every particle has a wall term, every step a stiff one at large K.
const std::vector<std::string> kWallsScene = {"thermal.walls=\"x-,x+,y-,y+,z-,z+\"",
                                              "thermal.wall_reach=1e-3",
                                              "material.initial_temperature=650"};

struct Outcome {
  std::string status;  // ok | refused | FAIL | interrupted
  bool bounded = true;
  double optics_error = 0, heat_error = 0, seconds = 0;
  std::string note;
  FinalState end;  // for the comparison of a group's solvers
};

std::vector<std::string> index_sets(const std::string& index) {
  if (index == "metal")
    return {"optics.n_solid=0.056", "optics.k_solid=4.276", "optics.n_liquid=0.056",
            "optics.k_liquid=4.276"};
  return {"optics.n_solid=" + index, "optics.n_liquid=" + index};
}

RunSources cell_sources(const Cell& c) {
  RunSources sources;
  sources.preset = "zohdi2013";
  sources.sets = {"pulses.count=2",
                  "beam.rays=200",
                  "pulses.duration=1e-13",
                  "material.conductivity=" + c.conductivity,
                  "thermal.solver=\"" + c.solver + "\"",
                  "packing.count=" + c.count,
                  "thermal.dt=" + c.dt,
                  "thermal.phi=" + c.phi};
  for (const auto& s : index_sets(c.index)) sources.sets.push_back(s);
  if (c.scene == "walls")
    sources.sets.insert(sources.sets.end(), kWallsScene.begin(), kWallsScene.end());
  // The stiffest real step: a whole pulses.period of cooling in one step (dt G / c up to ~1e9).
  if (c.dt == kCoolingStep) sources.sets.push_back("pulses.period=" + c.dt);
  return sources;
}

// The heat that solid particles hold beyond what they absorbed, over all the heat absorbed: sum
// over them of max(0, m_i C_S (theta_i - theta_0) / M - absorbed_i). Only conduction gives a
// particle more: one that crossed a latent band (and stayed, or fell back, below theta_m) holds
// less as sensible heat than it absorbed, and without walls nothing else adds heat.
double conducted_fraction(const Simulation& sim) {
  const Particles& p = sim.particles();
  const Material& m = sim.spec().materials[0];
  const double theta0 = sim.spec().packing.initial_temperature;
  const double total = sim.figures().energy.absorbed;
  double gained = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (!p.alive[i] || p.phase[i] != Phase::solid) continue;
    const double mass = p.volume(i) * m.density * m.c_solid / sim.spec().thermal.time_scaling;
    gained += std::max(0.0, mass * (p.temperature[i] - theta0) - sim.absorbed()[i]);
  }
  return total > 0 ? gained / total : 0;
}

// Bounded: no particle below the run's floor (the lesser of the initial and the walls'
// temperatures; below_floor allows round-off, 1e-12 of it: the bound was 1e-6 K before every
// cell was measured within this), none above the greater plus what all the absorbed energy could
// do to the lightest particle, and all finite. A latent band cannot take a particle past either.
bool bounded(const Simulation& sim) {
  const auto& t = sim.particles().temperature;
  const double lo = *std::min_element(t.begin(), t.end());
  const double hi = *std::max_element(t.begin(), t.end());
  double ceiling = sim.spec().packing.initial_temperature;
  for (const Wall& w : sim.spec().thermal.walls) ceiling = std::max(ceiling, w.temperature);
  const Material& m = sim.spec().materials[0];  // all share one material here
  double lightest = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < sim.particles().size(); ++i)
    lightest = std::min(lightest, sim.particles().volume(i));
  const double mass = std::isfinite(lightest)
                          ? lightest * m.density * m.c_solid / sim.spec().thermal.time_scaling
                          : 1.0;
  return std::isfinite(lo) && std::isfinite(hi) && !below_floor(lo, sim.temperature_floor()) &&
         hi <= ceiling + sim.figures().energy.absorbed / mass + 1e-6;
}

// Closed ledgers cannot see heat put in the wrong particle or conduction left out: at K = 0 (or
// alone) each particle keeps what it absorbed; at K > 0 the touching ones exchange heat; in the
// walls scene the walls at 300 K take heat from a bed at 650 K. "" when the cell conducts as it
// should, else why not.
std::string conduction_failure(const Cell& c, const Simulation& sim) {
  char note[200];
  if (c.scene == "walls") {
    const double walls = sim.figures().energy.walls;
    if (walls > 0) return "";
    std::snprintf(note, sizeof note,
                  "heat into the walls = %.2g J: must be > 0 (a bed at 650 K, walls at 300 K)",
                  walls);
    return note;
  }
  const double gained = conducted_fraction(sim);
  const bool conducts = c.conductivity != "0" && c.count != "1";
  if (conducts ? gained >= kConducted : gained <= kNoConduction) return "";
  std::snprintf(note, sizeof note,
                "heat solid particles hold beyond what they absorbed / heat absorbed = %.2g: "
                "must be %s %g %s",
                gained, conducts ? ">=" : "<=", conducts ? kConducted : kNoConduction,
                conducts ? "(K > 0, particles touch)" : "(nothing conducts)");
  return note;
}

// The checks of a cell that ran: bounded, ledgers closed, conduction where K says.
void check_run(const Cell& c, const Simulation& sim, Outcome& o) {
  const EnergyLedger e = sim.figures().energy;
  o.optics_error = std::abs(e.relative_optics_imbalance());
  o.heat_error = e.heat_error();
  o.bounded = bounded(sim);
  // The heat ledger closes to round-off whatever the solver: the iterative ones restore each
  // component's energy after they stop (they lost up to 1.8e-9 of it in the cooling cells
  // before, within the tolerance-sized bound this grid used to apply; the worst beam cell now is
  // 1.5e-12, docs/stability-report.txt).
  const bool iterated = sim.counts().iterative_heat_steps > 0;  // the factorisation: 1e-15
  const bool ledgers =
      o.optics_error < 1e-12 &&
      o.heat_error <= (c.scene == "walls" && iterated ? kWallsHeatRoundOff : 1e-10);
  const std::string conduction = conduction_failure(c, sim);
  o.status = o.bounded && ledgers && conduction.empty() ? "ok" : "FAIL";
  if (!ledgers) o.note = "ledger does not close";
  if (!conduction.empty()) o.note = conduction;
  o.end = {sim.particles().temperature, sim.particles().phase, sim.figures().vaporized_fraction};
}

Outcome run_cell(const Cell& c) {
  Outcome o;
  const auto start = std::chrono::steady_clock::now();
  try {
    const RunConfig config = load_run_config(cell_sources(c));
    Simulation sim(config.sim);
    sim.run(&stop_requested());
    if (!sim.done()) {
      o.status = "interrupted";
      return o;
    }
    check_run(c, sim, o);
  } catch (const InputError& e) {
    o.status = expected_refusal(c.solver, c.phi, e.what(), false) ? "refused" : "FAIL";
    o.note = e.what();
  } catch (const SolverRefusal& e) {  // any other RunError (a NaN found mid-run) is a failure
    o.status = expected_refusal(c.solver, c.phi, e.what(), true) ? "refused" : "FAIL";
    o.note = e.what();
  } catch (const std::exception& e) {
    o.status = "FAIL";
    o.note = e.what();
  }
  o.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return o;
}

// The solvers of a group solved the same problem: each one that ran must end where the direct
// solver did (or, where it did not run, the first that did). A disagreeing cell fails.
void compare_solvers(const std::vector<Cell>& group, std::vector<Outcome>& outcomes) {
  std::size_t ref = group.size();
  for (std::size_t k = 0; k < group.size(); ++k)
    if (outcomes[k].status == "ok" && (ref == group.size() || group[k].solver == "direct")) ref = k;
  for (std::size_t k = 0; k < group.size() && ref < group.size(); ++k) {
    if (k == ref || outcomes[k].status != "ok") continue;
    const std::string why = solver_disagreement(outcomes[ref].end, outcomes[k].end);
    if (why.empty()) continue;
    outcomes[k].status = "FAIL";
    outcomes[k].note = "differs from " + group[ref].solver + ": " + why;
  }
}

// Every cell of the grid, a group's solvers next to each other: phi = 1 over the whole grid, and
// slices at phi = 1/2 (Crank-Nicolson) and phi = 0 (explicit) where conduction makes phi matter:
// steps beyond their limit sub-stepped, or refused beyond thermal.max_substeps. (phi = 1/2 at
// K = 1e6 with 3000 particles, 1500 sub-steps a step, would take 76 s alone.) And the walls
// scene at phi = 1 wherever its walls conduct (K > 0), index 1.4.
std::vector<std::vector<Cell>> grid() {
  const std::vector<std::string> solvers{"fixed-point", "cg", "direct", "auto"};
  const std::vector<std::string> steps{"\"paper\"", "1e-13", "\"pulse\"", kCoolingStep};
  std::vector<std::vector<Cell>> groups;
  const auto add = [&](const Cell& c) {
    groups.emplace_back();
    for (const auto& s : solvers) {
      groups.back().push_back(c);
      groups.back().back().solver = s;
    }
  };
  for (const char* k : {"0", "100", "10000", "1000000"})
    for (const auto& dt : steps)
      for (const char* n : {"1.0", "1.4", "20", "metal"})
        for (const char* count : {"1", "100", "3000"}) add({k, dt, n, count, "1.0", ""});
  for (const std::string phi : {"0.5", "0.0"})
    for (const std::string k : {"100", "10000", "1000000"})
      for (const auto& dt : steps)
        for (const std::string count : {"100", "3000"})
          if (count == "100" || (phi == "0.5" && k != "1000000"))
            add({k, dt, "1.4", count, phi, ""});
  for (const char* k : {"100", "10000", "1000000"})
    for (const auto& dt : steps)
      for (const char* count : {"1", "100", "3000"}) add({k, dt, "1.4", count, "1.0", "", "walls"});
  return groups;
}

// The grid's columns, as the table heads them and `--only` names them.
struct Column {
  const char* name;
  std::string Cell::*value;
};
constexpr Column kColumns[] = {{"K", &Cell::conductivity}, {"dt", &Cell::dt},
                               {"index", &Cell::index},    {"N", &Cell::count},
                               {"phi", &Cell::phi},        {"solver", &Cell::solver},
                               {"scene", &Cell::scene}};

// A cell's value as a user writes it: "paper" for the table's "\"paper\"".
std::string unquoted(std::string v) {
  v.erase(std::remove(v.begin(), v.end(), '"'), v.end());
  return v;
}

// Whether a user's value names a grid value: as text, or as the same number ("1e6" is 1000000).
bool same_value(const std::string& wanted, const std::string& cell) {
  if (wanted == unquoted(cell)) return true;
  char *end_a = nullptr, *end_b = nullptr;
  const double a = std::strtod(wanted.c_str(), &end_a), b = std::strtod(cell.c_str(), &end_b);
  return !wanted.empty() && *end_a == '\0' && !cell.empty() && *end_b == '\0' && a == b;
}

// One `--only COLUMN=V1,V2`: the column and the values it keeps.
struct Selection {
  const Column* column;
  std::vector<std::string> values;
};

std::string column_names() {
  std::string names;
  for (const Column& c : kColumns) names += std::string(names.empty() ? "" : ", ") + c.name;
  return names;
}

// The grid's values of a column, in the grid's order, for a message.
std::string grid_values(const std::vector<std::vector<Cell>>& groups, const Column& column) {
  std::vector<std::string> seen;
  for (const auto& group : groups)
    for (const Cell& cell : group)
      if (std::find(seen.begin(), seen.end(), unquoted(cell.*column.value)) == seen.end())
        seen.push_back(unquoted(cell.*column.value));
  std::string list;
  for (const auto& v : seen) list += (list.empty() ? "" : ", ") + v;
  return list;
}

Selection read_selection(const std::string& only, const std::vector<std::vector<Cell>>& groups) {
  const std::size_t eq = only.find('=');
  const std::string name = only.substr(0, eq);
  const Column* column = nullptr;
  for (const Column& c : kColumns)
    if (name == c.name) column = &c;
  if (eq == std::string::npos || column == nullptr)
    throw InputError("validate --only `" + only +
                     "`: must be COLUMN=VALUE[,VALUE...], COLUMN one of " + column_names());
  Selection s{column, {}};
  std::size_t from = eq + 1;
  for (std::size_t comma; from <= only.size(); from = comma + 1) {
    comma = std::min(only.find(',', from), only.size());
    s.values.push_back(only.substr(from, comma - from));
    bool in_grid = false;
    for (const auto& group : groups)
      for (const Cell& cell : group) in_grid |= same_value(s.values.back(), cell.*column->value);
    if (!in_grid)
      throw InputError("validate --only " + name + " = `" + s.values.back() +
                       "`: not in the grid; its values are " + grid_values(groups, *column));
  }
  return s;
}

bool selected(const Cell& cell, const std::vector<Selection>& selections) {
  for (const Selection& s : selections) {
    const auto same = [&](const std::string& v) { return same_value(v, cell.*s.column->value); };
    if (std::none_of(s.values.begin(), s.values.end(), same)) return false;
  }
  return true;
}

// The grid `all` cut down to the cells every `--only` keeps (all of it without one); a group keeps
// its selected solvers, still compared with each other.
std::vector<std::vector<Cell>> selected_grid(const std::vector<std::vector<Cell>>& all,
                                             const std::vector<std::string>& only) {
  std::vector<Selection> selections;
  for (const auto& o : only) selections.push_back(read_selection(o, all));
  std::vector<std::vector<Cell>> groups;
  for (const auto& group : all) {
    std::vector<Cell> kept;
    for (const Cell& cell : group)
      if (selected(cell, selections)) kept.push_back(cell);
    if (!kept.empty()) groups.push_back(kept);
  }
  if (groups.empty()) {
    std::string asked;
    for (const auto& o : only) asked += " --only " + o;
    throw InputError("validate" + asked + ": no cell of the grid has all of these");
  }
  return groups;
}

}  // namespace

// The refusals the grid expects, each a documented limit of what the cell asks: the fixed-point
// iteration (3.11) past its contraction limit, CG at thermal.max_iterations, and phi < 1 beyond
// thermal.max_substeps. Any other refusal (a renamed key in the cell's settings, a validation that
// rejects valid input, CG breaking down) is a failure.
bool expected_refusal(const std::string& solver, const std::string& phi, const std::string& message,
                      bool solver_refusal) {
  const auto starts = [&](const char* prefix) { return message.rfind(prefix, 0) == 0; };
  if (solver_refusal && solver == "fixed-point")
    return starts("thermal fixed-point iteration (3.11) diverges at iteration");
  if (solver_refusal && solver == "cg")
    return starts("thermal conjugate gradients did not reach thermal.tolerance");
  return !solver_refusal && phi != "1.0" &&
         message.find(" sub-steps > thermal.max_substeps = ") != std::string::npos;
}

// Temperatures to kSolverAgreement, phases and the vaporised fraction exactly (to round-off).
std::string solver_disagreement(const FinalState& reference, const FinalState& other) {
  if (other.temperature.size() != reference.temperature.size())
    return std::to_string(other.temperature.size()) + " particles, not " +
           std::to_string(reference.temperature.size());
  double worst = 0;
  std::size_t phases = 0;
  for (std::size_t i = 0; i < reference.temperature.size(); ++i) {
    const double d = std::abs(other.temperature[i] - reference.temperature[i]);
    if (!std::isnan(worst) && !(d <= worst)) worst = d;  // a NaN too, and it stays
    phases += other.phase[i] != reference.phase[i];
  }
  const double dv = std::abs(other.vaporized_fraction - reference.vaporized_fraction);
  if (worst <= kSolverAgreement && phases == 0 && dv <= kRoundOff) return "";
  char why[200];
  std::snprintf(why, sizeof why,
                "max |dtheta| = %.3g K (limit %g K), %zu particles in another phase, vaporised "
                "fraction off by %.3g",
                worst, kSolverAgreement, phases, dv);
  return why;
}

int run_stability_report(bool quiet, const std::vector<std::string>& only) {
  const std::vector<std::vector<Cell>> all = grid();
  const std::vector<std::vector<Cell>> groups = selected_grid(all, only);
  const auto count = [](const std::vector<std::vector<Cell>>& grid_part) {
    std::size_t cells = 0;
    for (const auto& group : grid_part) cells += group.size();
    return cells;
  };
  const std::size_t cells = count(groups);
  if (!only.empty()) {
    std::printf("stability: %zu of the grid's %zu cells\n", cells, count(all));
    const bool alone = std::any_of(groups.begin(), groups.end(),
                                   [](const std::vector<Cell>& g) { return g.size() == 1; });
    if (alone)  // the check a cell passes alone is weaker: say so rather than pass it quietly
      std::printf(
          "stability: some cells are the only solver of their group selected: they are not "
          "compared with another solver (the direct one is every group's reference)\n");
  }
  int ok = 0, refused = 0, failed = 0;
  std::printf("%-8s %-9s %-6s %-6s %-4s %-12s %-6s %-8s %-8s %-10s %-10s %s\n", "K", "dt", "index",
              "N", "phi", "solver", "scene", "status", "bounded", "optics", "heat", "note");
  for (const auto& group : groups) {
    std::vector<Outcome> outcomes;
    for (const Cell& cell : group) {
      outcomes.push_back(run_cell(cell));
      if (outcomes.back().status != "interrupted") continue;
      // Ctrl-C: the groups so far stand, the rest never ran (nor compared)
      std::printf(
          "stability: interrupted after %d of %zu cells: %d passed, %d failed, %d refused\n",
          ok + failed + refused, cells, ok, failed, refused);
      return failed > 0 ? 1 : interrupted_exit_code();  // a failure is the graver news
    }
    compare_solvers(group, outcomes);
    for (std::size_t k = 0; k < group.size(); ++k) {
      const Cell& cell = group[k];
      const Outcome& o = outcomes[k];
      (o.status == "ok" ? ok : o.status == "refused" ? refused : failed) += 1;
      if (quiet && o.status != "FAIL") continue;  // a refusal is one the grid expects
      // A failure prints its whole message; a refusal the start of its reason.
      const std::string note = o.status == "FAIL" ? o.note : o.note.substr(0, 90);
      std::printf("%-8s %-9s %-6s %-6s %-4s %-12s %-6s %-8s %-8s %-10.1e %-10.1e %s\n",
                  cell.conductivity.c_str(), cell.dt.c_str(), cell.index.c_str(),
                  cell.count.c_str(), cell.phi.c_str(), cell.solver.c_str(), cell.scene.c_str(),
                  o.status.c_str(), o.bounded ? "yes" : "NO", o.optics_error, o.heat_error,
                  note.c_str());
    }
    std::fflush(stdout);
  }
  std::printf("stability: %d passed, %d failed, %d refused with a message\n", ok, failed, refused);
  return failed == 0 ? 0 : 1;
}

}  // namespace beampack::tools
