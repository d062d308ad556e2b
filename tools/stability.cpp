// `beampack validate --stiff`: a grid over conductivity, time step, index, particle count and
// solver. Each cell either runs, stays bounded and closes its ledgers, or is refused with a
// clear message; anything else (NaN, crash, unbounded temperature) is a failure.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
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

struct Cell {
  std::string conductivity, dt, index, count, solver;
};

struct Outcome {
  std::string status;  // ok | refused | FAIL
  bool bounded = true;
  double optics_error = 0, heat_error = 0, seconds = 0;
  std::string note;
};

std::vector<std::string> index_sets(const std::string& index) {
  if (index == "metal")
    return {"optics.n_solid=0.056", "optics.k_solid=4.276", "optics.n_liquid=0.056",
            "optics.k_liquid=4.276"};
  return {"optics.n_solid=" + index, "optics.n_liquid=" + index};
}

Outcome run_cell(const Cell& c) {
  RunSources sources;
  sources.preset = "zohdi2013";
  sources.sets = {"pulses.count=2",
                  "beam.rays=200",
                  "pulses.duration=1e-13",
                  "material.conductivity=" + c.conductivity,
                  "thermal.solver=\"" + c.solver + "\"",
                  "packing.count=" + c.count,
                  "thermal.dt=" + c.dt};
  for (const auto& s : index_sets(c.index)) sources.sets.push_back(s);
  // The stiffest real step: a whole pulses.period of cooling in one step (dt G / c up to ~1e9).
  if (c.dt == kCoolingStep) sources.sets.push_back("pulses.period=" + c.dt);
  Outcome o;
  const auto start = std::chrono::steady_clock::now();
  try {
    const RunConfig config = load_run_config(sources);
    Simulation sim(config.sim);
    sim.run(&stop_requested());
    if (!sim.done()) {
      o.status = "interrupted";
      return o;
    }
    const Figures f = sim.figures();
    const EnergyLedger& e = f.energy;
    o.optics_error = e.injected > 0 ? std::abs(e.optics_imbalance()) / e.injected : 0;
    o.heat_error = e.heat_error();
    // Bounded: no particle below the initial 300 K (nothing cools it without walls), none above
    // what all the absorbed energy could do to the lightest particle, and all finite.
    const auto& t = sim.particles().temperature;
    const double lo = *std::min_element(t.begin(), t.end());
    const double hi = *std::max_element(t.begin(), t.end());
    // The lightest particle's thermal mass m C_S / M (all share one material here).
    const Material& m = sim.spec().materials[0];
    double lightest = std::numeric_limits<double>::infinity();
    for (std::size_t i = 0; i < sim.particles().size(); ++i)
      lightest = std::min(lightest, sim.particles().volume(i));
    const double mass = std::isfinite(lightest)
                            ? lightest * m.density * m.c_solid / sim.spec().thermal.time_scaling
                            : 1.0;
    o.bounded = std::isfinite(lo) && std::isfinite(hi) && lo >= 300 - 1e-6 &&
                hi <= 300 + e.absorbed / mass + 1e-6;
    // The heat ledger closes to round-off whatever the solver: the iterative ones restore each
    // component's energy after they stop (they lost up to 1.8e-9 of it in the cooling cells
    // before, within the tolerance-sized bound this grid used to apply; the worst now is 4e-12).
    const bool ledgers = o.optics_error < 1e-12 && o.heat_error <= 1e-10;
    o.status = o.bounded && ledgers ? "ok" : "FAIL";
    if (!ledgers) o.note = "ledger does not close";
  } catch (const InputError& e) {
    o.status = "refused";
    o.note = e.what();
  } catch (const SolverRefusal& e) {  // any other RunError (a NaN found mid-run) is a failure
    o.status = "refused";
    o.note = e.what();
  } catch (const std::exception& e) {
    o.status = "FAIL";
    o.note = e.what();
  }
  o.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return o;
}

}  // namespace

int run_stability_report(bool quiet) {
  const std::vector<std::string> conductivities{"0", "100", "10000", "1000000"};
  const std::vector<std::string> steps{"\"paper\"", "1e-13", "\"pulse\"", kCoolingStep};
  const std::vector<std::string> indices{"1.0", "1.4", "20", "metal"};
  const std::vector<std::string> counts{"1", "100", "3000"};
  const std::vector<std::string> solvers{"fixed-point", "cg", "direct", "auto"};
  std::vector<Cell> cells;
  for (const auto& k : conductivities)
    for (const auto& dt : steps)
      for (const auto& n : indices)
        for (const auto& count : counts)
          for (const auto& solver : solvers) cells.push_back({k, dt, n, count, solver});
  int ok = 0, refused = 0, failed = 0;
  std::printf("%-8s %-9s %-6s %-6s %-12s %-8s %-8s %-10s %-10s %s\n", "K", "dt", "index", "N",
              "solver", "status", "bounded", "optics", "heat", "note");
  for (const Cell& cell : cells) {
    const Outcome o = run_cell(cell);
    if (o.status == "interrupted") {  // Ctrl-C: the cells so far stand, the rest never ran
      std::printf(
          "stability: interrupted after %d of %zu cells: %d passed, %d failed, %d refused\n",
          ok + failed + refused, cells.size(), ok, failed, refused);
      return 1;
    }
    (o.status == "ok" ? ok : o.status == "refused" ? refused : failed) += 1;
    if (quiet && o.status == "ok") continue;
    std::string note = o.note.substr(0, 90);
    std::printf("%-8s %-9s %-6s %-6s %-12s %-8s %-8s %-10.1e %-10.1e %s\n",
                cell.conductivity.c_str(), cell.dt.c_str(), cell.index.c_str(), cell.count.c_str(),
                cell.solver.c_str(), o.status.c_str(), o.bounded ? "yes" : "NO", o.optics_error,
                o.heat_error, note.c_str());
    std::fflush(stdout);
  }
  std::printf("stability: %d passed, %d failed, %d refused with a message\n", ok, failed, refused);
  return failed == 0 ? 0 : 1;
}

}  // namespace beampack::tools
