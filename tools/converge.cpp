// `beampack converge`: error against run time. Each ladder varies one resolution of the scene
// (time step, rays per pulse, solver tolerance); the finest rung is the reference.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <set>
#include <sstream>
#include <string>

#include "engine/simulation.h"
#include "geometry/error.h"
#include "tools/converge.h"
#include "tools/svg_plot.h"
#include "tools/writers.h"

namespace beampack::tools {
namespace fs = std::filesystem;
namespace {

// How far apart two runs' peak temperatures are; none for a scene without particles.
std::optional<double> peak_difference(const Figures& a, const Figures& b) {
  if (!a.max_temperature || !b.max_temperature) return std::nullopt;
  return std::abs(*a.max_temperature - *b.max_temperature);
}

// A temperature difference as printed: "12.5 K", or "-" where there is none (no particles).
std::string kelvin_text(std::optional<double> difference) {
  return shown(difference, "%.3g K", "-");
}

struct Rung {
  std::string value;  // the --set value
  RunResult result;
};

struct Ladder {
  std::string name, key;
  std::vector<std::string> values;  // finest first
  std::vector<RunConfig> configs;   // one per value, resolved before any run
  std::vector<Rung> rungs;          // the rungs that finished
  bool cut = false;                 // an interrupt left rungs out
};

std::vector<Ladder> ladders(const RunConfig& base) {
  const double paper_dt = paper_step(base.sim.packing, base.xi, base.packing.get());
  auto seconds = [](double v) {
    std::ostringstream s;
    s.precision(6);
    s << v;
    return s.str();
  };
  Ladder dt{"time step", "thermal.dt", {}, {}, {}};
  for (double f : {1.0, 4.0, 16.0, 64.0}) dt.values.push_back(seconds(f * paper_dt));
  dt.values.push_back("\"pulse\"");
  Ladder rays{"rays per pulse",
              "beam.rays",
              {"100000", "30000", "10000", "3000", "1000", "300", "100"},
              {},
              {}};
  Ladder tol{
      "solver tolerance", "thermal.tolerance", {"1e-12", "1e-10", "1e-8", "1e-6", "1e-4"}, {}, {}};
  return {dt, rays, tol};
}

// Runs every rung of the ladder that can run; a rung that fails is reported and left out, and an
// interrupted one is not kept (a part of a run is not a result). The reference is the finest
// rung, run first: without it the others have nothing to be compared with, so when it fails the
// ladder stops there. The spec warnings `said` for every rung are not said again. Returns the
// exit code so far.
int run_ladder(Ladder& ladder, bool quiet, const std::set<std::string>& said) {
  int code = 0;
  std::fflush(stdout);  // the last ladder's lines before this one's failures, when both are piped
  for (std::size_t k = 0; k < ladder.values.size(); ++k) {
    if (stop_requested().load()) {
      ladder.cut = true;
      break;
    }
    const std::string rung = ladder.name + " " + ladder.values[k], label = rung + ": ";
    try {
      RunResult r = run_scene(ladder.configs[k], quiet, label, said);
      say_warnings(label, r.run_warnings);  // its line comes with the table, after every rung
      if (r.interrupted) {
        std::fprintf(stderr,
                     "beampack: converge interrupted during %s; that rung and the rest "
                     "are not in convergence.csv\n",
                     rung.c_str());
        ladder.cut = true;
        break;
      }
      ladder.rungs.push_back({ladder.values[k], std::move(r)});
    } catch (const std::exception& e) {
      const bool reference = k == 0;
      code = std::max(code, report_failed_run(label, e,
                                              reference ? "the reference rung: ladder left out of "
                                                          "convergence.csv, its other rungs not run"
                                                        : "left out of convergence.csv"));
      if (reference) break;
    }
  }
  return code;
}

// Every error is against the finest rung, whose own error no rung measures: the step to the next
// rung is said, as the size that error may have (a review found the paper's step 10% off the
// converged v_v of a conducting scene, where the ladder's errors looked small).
void say_what_the_reference_leaves_unmeasured(const Ladder& ladder) {
  if (ladder.rungs.size() < 2) return;
  const RunResult& finest = ladder.rungs[0].result;
  const RunResult& next = ladder.rungs[1].result;
  std::printf(
      "%-18s the reference (%s) is %.2e in v_v and %s in peak temperature from the next rung "
      "(%s): its own error is not measured and may be of that size%s\n",
      ladder.name.c_str(), ladder.rungs[0].value.c_str(),
      std::abs(next.figures.vaporized_fraction - finest.figures.vaporized_fraction),
      kelvin_text(peak_difference(next.figures, finest.figures)).c_str(),
      ladder.rungs[1].value.c_str(),
      ladder.key == "thermal.dt" ? " (a lower pulses.xi refines the ladder)" : "");
  std::fflush(stdout);  // before any later warning on stderr, when both go to one pipe
}

// Why no step of the scene solves iteratively, so that thermal.tolerance changes no result; ""
// when some step may (thermal_model.cpp: only a conducting contact with phi > 0 builds a system,
// and "direct" factorises it).
std::string why_no_iterative_solve(const SimulationSpec& spec) {
  if (spec.thermal.solver == "direct")
    return "`thermal.solver` = \"direct\" factorises every step, with no tolerance";
  if (spec.thermal.phi == 0) return "`thermal.phi` = 0: explicit steps solve no system";
  if (!conducts_between_particles(spec))
    return "no contact conducts (`material.conductivity` = 0): each particle's step is solved "
           "on its own, without iterations";
  return "";
}

// The solver tolerance ladder when some step may solve iteratively; otherwise every rung would
// repeat the reference bit for bit (an all-zero ladder that looked measured): it is not run, and
// converge says so. Returns the note for the chart ("" when the ladder runs).
std::string drop_unmeasurable_ladders(std::vector<Ladder>& all, const SimulationSpec& spec) {
  const std::string why = why_no_iterative_solve(spec);
  if (why.empty()) return "";
  std::erase_if(all, [](const Ladder& l) { return l.key == "thermal.tolerance"; });
  std::fprintf(stderr,
               "beampack: note: converge: the solver tolerance ladder is not run: %s, so "
               "`thermal.tolerance` changes no result of this scene\n",
               why.c_str());
  return "solver tolerance ladder not run: no iterative solve in this scene";
}

// A ladder whose every rung ended exactly as its reference measured nothing: its key changed no
// result (say, "auto" factorised every step, so no tolerance applied). Said, as the errors of 0
// in the table and chart would otherwise read as a converged result.
void warn_if_no_rung_differs(const Ladder& ladder) {
  if (ladder.rungs.size() < 2) return;
  const RunResult& ref = ladder.rungs.front().result;
  for (const Rung& rung : ladder.rungs) {
    const RunResult& r = rung.result;
    if (r.figures.vaporized_fraction != ref.figures.vaporized_fraction ||
        r.temperature != ref.temperature || r.alive != ref.alive)
      return;
  }
  std::fflush(stdout);
  std::fprintf(stderr,
               "beampack: warning: converge: every rung of the %s ladder ended exactly as its "
               "reference: `%s` changed no result of this scene, so its errors of 0 measure "
               "nothing\n",
               ladder.name.c_str(), ladder.key.c_str());
}

// convergence.svg: the vaporised fraction's error (INTERFACE.md's chart) above the final
// temperature field's L2 error, each against wall seconds, log-log; a ladder is a series of its
// rungs but the reference.
std::vector<Chart> convergence_panels(const std::string& note) {
  return {Chart{"error of the vaporised fraction against run time",
                "wall seconds",
                "|v_v - v_v(finest)|",
                true,
                true,
                {},
                {},
                note},
          Chart{"L2 error of the final temperatures against run time",
                "wall seconds",
                "L2 error of T, K",
                true,
                true,
                {},
                {},
                note}};
}

}  // namespace

TemperatureError temperature_error(const RunResult& rung, const RunResult& reference) {
  TemperatureError e;
  double squares = 0, largest = 0;
  for (std::size_t i = 0; i < rung.temperature.size(); ++i) {
    if (!(rung.alive[i] && reference.alive[i])) continue;
    const double d = std::abs(rung.temperature[i] - reference.temperature[i]);
    squares += d * d;
    largest = std::max(largest, d);
    ++e.compared;
  }
  if (e.compared == 0) return e;
  e.l2 = std::sqrt(squares / double(e.compared));
  e.max = largest;
  return e;
}

namespace {

// Each rung's run file: the base's sources with the ladder's key at the rung's value.
void configure_rungs(Ladder& ladder, const RunSources& base) {
  for (const std::string& value : ladder.values) {
    RunSources sources = base;
    sources.swept = ladder.key + "=" + value;
    sources.swept_origin = "converge's " + ladder.name + " ladder, " + ladder.key + " = " + value;
    ladder.configs.push_back(load_run_config(sources));
    ladder.configs.back().packing.reset();  // each rung reads its packing when it runs
    refuse_run_only_outputs(ladder.configs.back(), "converge");
  }
}

// A ladder that ran: each rung's errors against the reference (its finest rung) as a row of
// convergence.csv and a printed line, and the rungs but the reference as a series of each panel.
void tabulate_ladder(const Ladder& ladder, std::string& csv, std::vector<Chart>& panels) {
  const RunResult& ref = ladder.rungs.front().result;
  const bool absorbed = ref.figures.energy.absorbed > 0;
  std::fflush(stdout);
  if (!absorbed)  // no pulse, no particle, or a beam that meets none
    std::fprintf(stderr,
                 "beampack: warning: converge: the %s ladder's reference run absorbed no "
                 "energy, so every error of it is 0 and measures nothing\n",
                 ladder.name.c_str());
  Series vv_series{ladder.name, {}, {}}, t_series{ladder.name, {}, {}};
  for (const Rung& rung : ladder.rungs) {
    const RunResult& r = rung.result;
    const double vv_error = std::abs(r.figures.vaporized_fraction - ref.figures.vaporized_fraction);
    const TemperatureError t = temperature_error(r, ref);
    const std::optional<double> peak_error = peak_difference(r.figures, ref.figures);
    std::ostringstream row;
    row << ladder.name << ',' << ladder.key << ',' << rung.value << ',' << exact(r.wall_seconds)
        << ',' << r.counts.steps << ',' << r.counts.rays << ','
        << exact(r.figures.vaporized_fraction) << ',' << exact(vv_error) << ',' << exact(t.l2)
        << ',' << exact(t.max) << ',' << t.compared << ',' << exact(r.figures.time) << ','
        << exact(r.figures.max_temperature) << ',' << exact(peak_error) << ','
        << stage_cells(r.stages) << '\n';
    csv += row.str();
    std::printf("%-18s %-22s %9.3f s  v_v = %.4f  error %.2e  T L2 error %s  peak error %s\n",
                ladder.name.c_str(), rung.value.c_str(), r.wall_seconds,
                r.figures.vaporized_fraction, vv_error, kelvin_text(t.l2).c_str(),
                kelvin_text(peak_error).c_str());
    std::fflush(stdout);
    if (&rung != &ladder.rungs.front()) {  // 0 (equal to the reference): in the 0 band
      vv_series.x.push_back(r.wall_seconds);
      vv_series.y.push_back(vv_error);
      t_series.x.push_back(r.wall_seconds);
      t_series.y.push_back(t.l2.value_or(std::nan("")));  // none compared: no point
    }
  }
  panels[0].series.push_back(vv_series);
  panels[1].series.push_back(t_series);
  say_what_the_reference_leaves_unmeasured(ladder);
  if (absorbed) warn_if_no_rung_differs(ladder);
}

// convergence.csv's columns before each run's stage seconds (stage_columns).
constexpr const char* kConvergenceColumns =
    "ladder,key,resolution,wall_seconds,steps,rays,vaporized_fraction,vaporized_fraction_error,"
    "temperature_l2_error_K,temperature_max_error_K,temperature_particles,end_time_s,"
    "peak_temperature_K,peak_temperature_error_K,";

// Every rung that ran to its end, labelled as its lines are, for the stage table.
std::vector<LabelledRun> labelled_runs(const std::vector<Ladder>& all) {
  std::vector<LabelledRun> runs;
  for (const Ladder& ladder : all)
    for (const Rung& rung : ladder.rungs)
      runs.push_back({ladder.name + " " + rung.value, rung.result.stages, rung.result.counts});
  return runs;
}

}  // namespace

int converge_command(const RunOptions& options) {
  note_reading_input();
  RunSources read_xi = options.sources;
  read_xi.xi_always_read = true;  // the time-step ladder is made of xi R / c
  read_xi.read_once();            // and every rung reads it again: a pipe's bytes come only once
  RunConfig base = load_run_config(read_xi);
  warn_of_input({&base});  // the rungs' runs read the same keys
  const auto threads = limit_threads(options.threads);
  const OutDir out_folder(options.out_dir);  // an unusable --out fails before the runs, not after
  const fs::path out(options.out_dir);
  const std::vector<std::string> tables = {"convergence.csv", "convergence.svg"};
  refuse_non_files_at_outputs(out, tables);
  std::vector<Ladder> all = ladders(base);
  std::vector<Chart> panels = convergence_panels(drop_unmeasurable_ladders(all, base.sim));
  base.packing.reset();  // each rung reads its packing when it runs: one copy at a time
  for (Ladder& ladder : all) configure_rungs(ladder, read_xi);  // a bad rung fails before any run
  std::vector<const RunConfig*> rungs;
  for (const Ladder& ladder : all)
    for (const RunConfig& config : ladder.configs) rungs.push_back(&config);
  const std::set<std::string> said = warn_of_shared_specs(rungs);
  std::string csv = std::string(kConvergenceColumns) + stage_columns() + "\n";
  int code = 0;
  for (Ladder& ladder : all) {
    code = std::max(code, run_ladder(ladder, options.quiet, said));
    if (ladder.rungs.empty()) continue;
    tabulate_ladder(ladder, csv, panels);
  }
  const bool no_rung =
      std::all_of(all.begin(), all.end(), [](const Ladder& l) { return l.rungs.empty(); });
  const bool cut = std::any_of(all.begin(), all.end(), [](const Ladder& l) { return l.cut; });
  if (no_rung) {  // a table of no rows is no result
    say_nothing_written(cut ? "converge interrupted before any rung ended"
                            : "converge: every ladder's reference rung failed",
                        out, tables);
    return cut && code == 0 ? interrupted_exit_code() : code;
  }
  StageTime output;
  {
    const StageTimer timer(output);
    write_atomically(
        {{(out / "convergence.csv").string(), [&](std::ostream& o) { o << csv; }},
         {(out / "convergence.svg").string(), [&](std::ostream& o) { o << render_svg(panels); }}});
  }
  for (const std::string& line : stage_total_lines(labelled_runs(all), output))
    std::printf("%s\n", line.c_str());
  std::printf("converge: %s/convergence.csv, %s/convergence.svg\n", options.out_dir.c_str(),
              options.out_dir.c_str());
  return cut && code == 0 ? interrupted_exit_code() : code;
}

}  // namespace beampack::tools
