// What a spec or a finished run says of its own physics, as text (simulation.h: spec_warnings,
// Simulation::run_warnings): legal runs whose numbers a caller should not trust without a look.
// The command line prints each line as `beampack: warning: <text>`.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "engine/simulation.h"

namespace beampack {
namespace {

// The "s" of a count's noun: "1 step", "2 steps".
const char* plural(std::uint64_t count) {
  return count == 1 ? "" : "s";
}

// A fixed thermal.dt far below the light's crossing time of the sample makes a run of millions
// of steps per pulse: legal (the budget per step is c dt), but said before it starts.
void warn_of_many_steps(const SimulationSpec& spec, std::vector<std::string>& out) {
  char text[640];
  // A period in seconds is stepped through whole, rays or not: pulse k starts at k T_p, so the last
  // starts after (count - 1) x period / dt steps.
  const double periods = spec.dt > 0 ? (spec.pulses.count - 1) * spec.pulses.period / spec.dt : 0.0;
  if (periods >= 1e7) {
    std::snprintf(text, sizeof text,
                  "`pulses.count` = %d pulses of `pulses.period` = %g s in steps of "
                  "`thermal.dt` = %g s: %.3g steps at least; a longer thermal.dt cools between "
                  "pulses in fewer steps",
                  spec.pulses.count, spec.pulses.period, spec.dt, periods);
    out.emplace_back(text);
  }
  const double steps = steps_per_crossing(spec);
  if (steps < 1e6) return;
  const double crossing = spec.packing.sample_size / kSpeedOfLight;
  std::snprintf(text, sizeof text,
                "`thermal.dt` = %g s: light crosses the sample (%g m) in %.3g s, %.3g steps of "
                "this length per crossing; `thermal.dt = \"pulse\"` takes one step per pulse "
                "flight",
                spec.dt, spec.packing.sample_size, crossing, steps);
  out.emplace_back(text);
}

// pi K R with K = 0: walls that take no heat. Legal (a sweep over K passes through 0), but not
// what a run that names walls usually wants.
void warn_if_walls_take_no_heat(const SimulationSpec& spec, std::vector<std::string>& out) {
  const auto& walls = spec.thermal.walls;
  if (walls.empty() || walls.front().conductance >= 0 || spec.materials.empty() ||
      spec.materials.front().conductivity > 0)
    return;
  out.emplace_back(
      "`thermal.walls` with `thermal.wall_conductance` = -1 (pi K R) and "
      "`material.conductivity` = 0: the walls take no heat; give thermal.wall_conductance in W/K "
      "for walls that do");
}

// A bed that starts at or above a material's melting temperature starts liquid (phase_at): legal
// (a bed preheated into the melt), but every such particle counts as melted before the beam
// comes, which a preheated solid bed set one kelvin too high did not mean.
void warn_if_bed_starts_liquid(const SimulationSpec& spec, std::vector<std::string>& out) {
  for (std::size_t k = 0; k < spec.materials.size(); ++k) {
    const Material& m = spec.materials[k];
    const double start = spec.packing.initial_temperature;
    if (!(start >= m.melt_temperature && start < m.vapor_temperature)) continue;
    const std::string table =
        spec.materials.size() == 1 ? "material" : "material[" + std::to_string(k) + "]";
    char text[640];
    std::snprintf(text, sizeof text,
                  "`material.initial_temperature` = %g K is at or above `%s.melt_temperature` = "
                  "%g K: its particles start liquid (index `optics.n_liquid`, `%s.c_liquid`) and "
                  "count in the melted fraction before any pulse; a solid bed starts below it",
                  start, table.c_str(), m.melt_temperature, table.c_str());
    out.emplace_back(text);
  }
}

// Pulses start at step boundaries: a pulses.period shorter than a step delays them.
void warn_of_late_pulses(const SimulationSpec& spec, const Counts& counts,
                         std::vector<std::string>& out) {
  if (counts.late_pulses == 0) return;
  char text[640];
  std::snprintf(
      text, sizeof text,
      "%llu of %d pulses started more than 1%% of `pulses.period` = %g s after k x period (up to "
      "%g s late): a pulse starts at a step boundary, and %s; use a fixed `thermal.dt` that "
      "divides the period",
      static_cast<unsigned long long>(counts.late_pulses), spec.pulses.count, spec.pulses.period,
      counts.max_pulse_delay,
      spec.dt > 0
          ? "`thermal.dt` does not divide the period"
          : "with `thermal.dt` = \"pulse\" a step is a whole pulse flight, longer than the period");
  out.emplace_back(text);
}

// The latent-heat corrector re-solves a step at most a few times (section 4); one that still
// found a new band at its last pass left that band's latent heat out.
void warn_of_capped_phase_steps(const SimulationSpec& spec, const Counts& counts,
                                std::vector<std::string>& out) {
  if (counts.capped_phase_steps == 0) return;
  char text[640];
  std::snprintf(
      text, sizeof text,
      "%llu heat steps stopped the latent-heat correction at its cap of %d passes while a "
      "particle still crossed a new band (theta_m or theta_v): that band's latent heat is missing "
      "from the step; a shorter `thermal.dt` crosses fewer bands per step",
      static_cast<unsigned long long>(counts.capped_phase_steps),
      spec.thermal.max_phase_corrections);
  out.emplace_back(text);
}

// Section 4 charges a latent band on the predictor's crossing; where the band then stops the step
// short of theta_m (or theta_v), it was charged for no phase change, and a stiff step (a wall, a
// high K) can charge it step after step: a liquid bed cooled by a wall released many times its
// heat while it stayed liquid, and a sphere heated hard stayed solid at 308 K under a vaporisation
// band charged from 99.9% of the heat it absorbed (so the absorbed heat, the threshold before,
// could never be passed in a run that only heats). Past a quarter of the heat the run moved
// (EnergyLedger::heat_scale) the bands shape its result.
void warn_of_bands_short(const Counts& counts, const EnergyLedger& e,
                         std::vector<std::string>& out) {
  constexpr double kShare = 0.25;  // the paper's example: 9% at one step per pulse flight
  if (!(counts.band_heat_short > kShare * e.heat_scale())) return;
  char text[720];
  std::snprintf(
      text, sizeof text,
      "%.3g J of latent heat was charged in %llu particle (sub-)steps whose crossing of theta_m or "
      "theta_v the band then stopped short of, %.0f%% of the %.3g J of heat the run moved: the "
      "paper's predictor-corrector (section 4) charges a band for the predicted crossing, so a "
      "particle a stiff step heats can be held below the crossing (a vaporisation band keeping it "
      "solid), and one it cools (walls, high conductivity) above it, step after step; the "
      "vaporised and melted fractions may be off by it; a shorter `thermal.dt` charges it for "
      "less",
      counts.band_heat_short, static_cast<unsigned long long>(counts.bands_short),
      100 * counts.band_heat_short / e.heat_scale(), e.heat_scale());
  out.emplace_back(text);
}

// The stagger redoes a step while a phase change alters the optics of a particle the rays met; in
// some steps the phases never settle (MODEL.md section 5, step 4).
void warn_of_unsettled_staggers(const SimulationSpec& spec, const Counts& counts,
                                std::vector<std::string>& out) {
  char text[640];
  if (counts.capped_stagger_steps > 0) {
    std::snprintf(
        text, sizeof text,
        "%llu step%s reached `thermal.max_staggers` = %d redos with the optics still changing: "
        "their result is the last redo's and depends on the cap; raise it or shorten "
        "`thermal.dt`",
        static_cast<unsigned long long>(counts.capped_stagger_steps),
        plural(counts.capped_stagger_steps), spec.max_staggers);
    out.emplace_back(text);
  }
  // Said where the phases so decided could move the fractions by more than 1e-3 of the
  // particles: at 10^5 and 10^6 particles nearly every step cycles, over a few particles each (65
  // decisions in 18 steps of 10^5 particles), and the warning said nothing worth a look.
  const double share = counts.particles > 0 ? static_cast<double>(counts.stagger_cycle_particles) /
                                                  static_cast<double>(counts.particles)
                                            : 0.0;
  if (counts.stagger_cycles > 0 && share > 1e-3) {
    std::snprintf(
        text, sizeof text,
        "in %llu step%s the stagger's redos alternated between two sets of phases (a particle "
        "melts when traced solid and does not when traced liquid, or the like): each such step "
        "keeps the second pass of the cycle, which decided %llu particle phase%s (%.2g of the "
        "particles): the melted and vaporised fractions may be off by about that much",
        static_cast<unsigned long long>(counts.stagger_cycles), plural(counts.stagger_cycles),
        static_cast<unsigned long long>(counts.stagger_cycle_particles),
        counts.stagger_cycle_particles == 1 ? "" : "s", share);
    out.emplace_back(text);
  }
}

// pulses.duration sets a pulse's energy, P tau (MODEL.md section 2), and its rays deliver that
// within their flight (section 5), however long tau is. Each pulse has the period, or with
// "auto" its rays' flight, before the next: a tau far beyond that was read as a pulse lasting
// tau, and was not one (the heat saw flashes). Judged on a finished run: part way, the time so far
// is no pulse's whole share.
void warn_of_flashed_pulses(const SimulationSpec& spec, const Figures& f, bool done,
                            std::vector<std::string>& out) {
  if (!done || f.pulse == 0) return;
  const bool auto_period = !(spec.pulses.period > 0);
  const double share = auto_period ? f.time / f.pulse : spec.pulses.period;
  const double tau = spec.pulses.duration;
  if (!(share > 0) || !(tau > 2 * share)) return;
  char text[800];
  std::snprintf(
      text, sizeof text,
      "`pulses.duration` = %g s sets each pulse's energy (`beam.power` x duration = %.3g J), "
      "which its rays deliver within their flight, not over the duration (MODEL.md section 5): "
      "each pulse had %.3g s (%s) before the next, so the heat saw %.3g W on average, %.3g times "
      "`beam.power` = %g W; %s",
      tau, spec.beam.power * tau, share,
      auto_period ? "its rays' mean flight, with `pulses.period` = \"auto\"" : "`pulses.period`",
      spec.beam.power * tau / share, tau / share, spec.beam.power,
      auto_period ? "for heat spread over time give more pulses of a shorter duration, with "
                    "`pulses.period` set"
                  : "a duration longer than the period adds energy, not time: give "
                    "`pulses.duration` <= `pulses.period`");
  out.emplace_back(text);
}

}  // namespace

double steps_per_crossing(const SimulationSpec& s) {
  return s.dt > 0 ? s.packing.sample_size / kSpeedOfLight / s.dt : 0.0;
}

std::string least_step_limit(const SimulationSpec& spec) {
  const double crossing = spec.packing.sample_size / kSpeedOfLight;
  return "must be >= sample.size / c / 1e9 = " + shown_number(crossing / kMaxStepsPerCrossing) +
         " s (light crosses the sample in " + shown_number(crossing) + " s)";
}

std::vector<std::string> spec_warnings(const SimulationSpec& spec) {
  std::vector<std::string> out;
  warn_of_many_steps(spec, out);
  warn_if_walls_take_no_heat(spec, out);
  warn_if_bed_starts_liquid(spec, out);
  return out;
}

std::vector<std::string> open_ledger_warnings(const SimulationSpec& spec, const EnergyLedger& e) {
  const double optics = std::abs(e.relative_optics_imbalance());
  const double heat = e.heat_error();
  const double heat_limit = EnergyLedger::heat_tolerance(spec.thermal.tolerance);
  std::vector<std::string> out;
  char text[640];
  if (!(optics <= EnergyLedger::kOpticsTolerance)) {  // NaN included
    std::snprintf(text, sizeof text,
                  "the optics ledger is open by %.3g of the injected energy "
                  "(round-off is ~1e-15): please report this run file",
                  optics);
    out.emplace_back(text);
  }
  if (!(heat <= heat_limit)) {
    std::snprintf(
        text, sizeof text,
        "the heat ledger is open by %.3g of the energy it moves (the larger of the heat in, "
        "absorbed and from walls, and out, stored, vaporised and to walls; more than %.3g, from "
        "`thermal.tolerance` = %g). Every solver keeps each cluster's "
        "energy to round-off, so the likely cause is a step whose temperature rises are "
        "below ~1e-13 of the temperatures (a faint beam, large or dense particles, "
        "`thermal.time_scaling` near 1): doubles cannot hold them; raise "
        "`thermal.time_scaling` or the energy of a step. Otherwise please report this run file",
        heat, heat_limit, spec.thermal.tolerance);
    out.emplace_back(text);
  }
  return out;
}

std::optional<std::string> phase_resolution_warning(const SimulationSpec& spec, const Figures& f,
                                                    const Counts& counts) {
  // Without a solve there is no tolerance to blame: no conduction, or explicit steps (phi = 0).
  if (spec.materials.empty() || !needs_conduction(spec) || spec.thermal.phi == 0)
    return std::nullopt;
  double gap = std::numeric_limits<double>::infinity();
  for (const Material& m : spec.materials)
    gap = std::min(gap, m.vapor_temperature - m.melt_temperature);
  // Relative accuracy of a step's solve: the tolerance where an iteration solved one, else
  // round-off ("auto" that factorised every step warned as if it had iterated: a false alarm).
  const double accuracy =
      counts.iterative_heat_steps > 0 ? std::max(spec.thermal.tolerance, 1e-15) : 1e-15;
  if (!f.max_temperature) return std::nullopt;  // no particles
  const double rise = *f.max_temperature - spec.packing.initial_temperature;
  const double misplaced = accuracy * rise;
  if (!(misplaced > 0.1 * gap)) return std::nullopt;
  char text[640];
  std::snprintf(
      text, sizeof text,
      "the peak temperature rose %.3g K, and the heat solves, accurate to %.3g of a step's largest "
      "change (`thermal.tolerance`, or round-off), may misplace a particle beside the hottest by "
      "~%.3g K, against %.3g K between `material.melt_temperature` and `vapor_temperature`: "
      "whether such a particle melted or vaporised may depend on the solver (a review saw one end "
      "2 K below its initial temperature); lower `thermal.tolerance` or the energy of a pulse",
      rise, accuracy, misplaced, gap);
  return std::string(text);
}

std::optional<std::string> below_floor_warning(const SimulationSpec& spec, double floor,
                                               const Particles& p, const Counts& counts) {
  std::size_t below = 0, coldest = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (!below_floor(p.temperature[i], floor)) continue;
    if (below++ == 0 || p.temperature[i] < p.temperature[coldest]) coldest = i;
  }
  if (below == 0) return std::nullopt;
  char cause[200];
  if (counts.iterative_heat_steps > 0)
    std::snprintf(cause, sizeof cause,
                  "the heat solves' error did it; lower `thermal.tolerance` (%g) or use "
                  "thermal.solver = \"direct\"",
                  spec.thermal.tolerance);
  else  // the factorisation, explicit or diagonal steps: round-off cannot go so far
    std::snprintf(cause, sizeof cause,
                  "no iterative solve ran, whose error could do it: please report this run file");
  char text[640];
  std::snprintf(text, sizeof text,
                "%zu particle%s ended below %.6g K, the least of the starting and wall "
                "temperatures, which heating, conduction, walls and latent bands cannot go below "
                "(particle %zu: %.3g K below it): %s",
                below, plural(below), floor, coldest, floor - p.temperature[coldest], cause);
  return text;
}

std::vector<std::string> Simulation::run_warnings() const {
  const Counts c = counts();
  const Figures f = figures();
  std::vector<std::string> out;
  warn_of_late_pulses(spec_, c, out);
  warn_of_flashed_pulses(spec_, f, done(), out);
  warn_of_capped_phase_steps(spec_, c, out);
  warn_of_bands_short(c, f.energy, out);
  warn_of_unsettled_staggers(spec_, c, out);
  for (std::string& warning : open_ledger_warnings(spec_, f.energy))
    out.push_back(std::move(warning));
  if (std::optional<std::string> warning = phase_resolution_warning(spec_, f, c))
    out.push_back(std::move(*warning));
  if (std::optional<std::string> warning =
          below_floor_warning(spec_, temperature_floor_, particles_, c))
    out.push_back(std::move(*warning));
  if (const std::size_t failed = tracer_->failed_scene_rebuilds(); failed > 0)
    out.push_back("the ray scene's background rebuild failed " + std::to_string(failed) + " time" +
                  plural(failed) + " (the last: " + tracer_->last_failed_scene_rebuild() +
                  "); the traces went on with the structure before it, in which the removed "
                  "particles are masked: the results are those of a rebuilt scene, only traced "
                  "slower");
  return out;
}

}  // namespace beampack
