// `beampack converge`: error against run time. Each ladder varies one resolution of the scene
// (time step, rays per pulse, solver tolerance); the finest rung is the reference.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <sstream>

#include "geometry/error.h"
#include "tools/converge.h"
#include "tools/svg_plot.h"
#include "tools/writers.h"

namespace beampack::tools {
namespace fs = std::filesystem;
namespace {

struct Rung {
  std::string value;  // the --set value
  RunResult result;
};

struct Ladder {
  std::string name, key;
  std::vector<std::string> values;  // finest first
  std::vector<Rung> rungs;
};

std::vector<Ladder> ladders(const RunConfig& base) {
  const double paper_dt = base.paper_dt;
  auto seconds = [](double v) {
    std::ostringstream s;
    s.precision(6);
    s << v;
    return s.str();
  };
  Ladder dt{"time step", "thermal.dt", {}, {}};
  for (double f : {1.0, 4.0, 16.0, 64.0}) dt.values.push_back(seconds(f * paper_dt));
  dt.values.push_back("\"pulse\"");
  Ladder rays{"rays per pulse", "beam.rays", {"100000", "30000", "10000", "3000", "1000", "300", "100"}, {}};
  Ladder tol{"solver tolerance", "thermal.tolerance", {"1e-12", "1e-10", "1e-8", "1e-6", "1e-4"}, {}};
  return {dt, rays, tol};
}

double l2_error(const std::vector<double>& a, const std::vector<double>& b) {
  double s = 0;
  for (std::size_t i = 0; i < a.size(); ++i) s += (a[i] - b[i]) * (a[i] - b[i]);
  return a.empty() ? 0 : std::sqrt(s / double(a.size()));
}

double max_error(const std::vector<double>& a, const std::vector<double>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(a[i] - b[i]));
  return m;
}

}  // namespace

int converge_command(const RunOptions& options) {
  const RunConfig base = load_run_config(options.sources);
  const auto threads = limit_threads(options.threads);
  std::vector<Ladder> all = ladders(base);
  std::string csv = "ladder,key,value,wall_seconds,steps,rays,vaporized_fraction,vaporized_fraction_error,"
                    "temperature_l2_error_K,temperature_max_error_K\n";
  Chart chart{"error of the vaporised fraction against run time", "wall seconds",
              "|v_v - v_v(finest)|", true, true, {}};
  for (Ladder& ladder : all) {
    for (const std::string& value : ladder.values) {
      if (stop_requested().load()) break;
      RunSources sources = options.sources;
      sources.sets.push_back(ladder.key + "=" + value);
      Rung rung{value, run_scene(load_run_config(sources), options.quiet, ladder.name + " " + value + ": ")};
      ladder.rungs.push_back(std::move(rung));
    }
    if (ladder.rungs.empty()) continue;
    const RunResult& ref = ladder.rungs.front().result;
    Series series{ladder.name, {}, {}};
    for (const Rung& rung : ladder.rungs) {
      const RunResult& r = rung.result;
      const double vv_error = std::abs(r.figures.vaporized_fraction - ref.figures.vaporized_fraction);
      std::ostringstream row;
      row << ladder.name << ',' << ladder.key << ',' << rung.value << ',' << exact(r.wall_seconds)
          << ',' << r.counts.steps << ',' << r.counts.rays << ',' << exact(r.figures.vaporized_fraction)
          << ',' << exact(vv_error) << ',' << exact(l2_error(r.temperature, ref.temperature)) << ','
          << exact(max_error(r.temperature, ref.temperature)) << '\n';
      csv += row.str();
      std::printf("%-18s %-22s %9.3f s  v_v = %.4f  error %.2e  T L2 error %.3g K\n", ladder.name.c_str(),
                  rung.value.c_str(), r.wall_seconds, r.figures.vaporized_fraction, vv_error,
                  l2_error(r.temperature, ref.temperature));
      std::fflush(stdout);
      if (&rung != &ladder.rungs.front()) {
        series.x.push_back(r.wall_seconds);
        // A rung that matches the reference exactly sits at the floor of the log axis.
        series.y.push_back(std::max(vv_error, 1e-6));
      }
    }
    chart.series.push_back(series);
  }
  prepare_out_dir(options.out_dir);
  const fs::path out(options.out_dir);
  write_atomically((out / "convergence.csv").string(), [&](std::ostream& o) { o << csv; });
  write_atomically((out / "convergence.svg").string(), [&](std::ostream& o) { o << render_svg(chart); });
  std::printf("converge: %s/convergence.csv, %s/convergence.svg\n", options.out_dir.c_str(),
              options.out_dir.c_str());
  return stop_requested().load() ? 1 : 0;
}

}  // namespace beampack::tools
