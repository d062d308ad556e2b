#include "engine/simulation.h"

#include "engine/memory_need.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>

#include "geometry/check.h"
#include "geometry/compensated_sum.h"
#include "geometry/contact.h"
#include "geometry/error.h"

namespace beampack {
namespace {

enum Stage { kTrace, kHeat, kPhases, kStagger, kRebuild };

class StageClock {
 public:
  // counts_call = false: the time is the stage's, the call is not one of its steps (a launch).
  explicit StageClock(StageTime& stage, bool counts_call = true)
      : stage_(stage), counts_call_(counts_call), start_(std::chrono::steady_clock::now()) {}
  ~StageClock() {
    stage_.seconds +=
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    stage_.calls += counts_call_;
  }

 private:
  StageTime& stage_;
  bool counts_call_;
  std::chrono::steady_clock::time_point start_;
};

}  // namespace

bool conducts_between_particles(const SimulationSpec& spec) {
  return std::any_of(spec.materials.begin(), spec.materials.end(),
                     [](const Material& m) { return m.conductivity > 0; });
}

bool needs_conduction(const SimulationSpec& spec) {
  return !spec.thermal.walls.empty() || conducts_between_particles(spec);
}

bool builds_ray_scene(const SimulationSpec& spec) {
  return spec.pulses.count > 0;
}

// Without pulses no step conducts, and no resumed state has rays that would: read_state refuses
// live rays without a launch, and launches beyond pulses.count.
bool builds_contact_graph(const SimulationSpec& spec) {
  return builds_ray_scene(spec) && needs_conduction(spec);
}

namespace {

// spec.packing, once the scene it makes is known to fit this machine (a file's is judged once
// read, by the constructor).
const PackingSpec& packing_that_fits(const SimulationSpec& spec) {
  refuse_beyond_memory(spec, machine_memory());
  return spec.packing;
}

}  // namespace

Simulation::Simulation(SimulationSpec spec)
    : Simulation(spec, make_packing(packing_that_fits(spec)), true) {}

Simulation::Simulation(SimulationSpec spec, Particles particles)
    : Simulation(spec, std::move(particles), spec.packing.source == "file") {}  // a file's, read

Simulation::Simulation(SimulationSpec spec, Particles particles, bool packing_from_spec)
    : spec_(std::move(spec)),
      particles_(std::move(particles)),
      packing_from_spec_(packing_from_spec) {
  // A caller's particles, or a file's (a library caller may have read them without the reader's
  // checks); generated ones were made with these checks, and the thermal-mass check below names
  // the key behind a radius that fails them.
  if (!generated_packing()) check_particles(particles_);
  // The rays, the ray scene and the contacts are made below: a scene that cannot fit is refused
  // before them, not by std::bad_alloc part way (a library caller's 10^9 rays).
  if (!packing_from_spec_)
    refuse_beyond_memory_of_given(spec_, machine_memory(), particles_.size());
  else if (spec_.packing.source == "file")
    refuse_beyond_memory(spec_, machine_memory(), particles_.size());
  mark_dead_as_vapour();
  check_run_numbers();
  check_thermal_masses(set_up_beam() * std::max(spec_.pulses.count, 1));
  set_up_tracer();
  set_up_thermal();
  check_step_limit();
  absorbed_.assign(particles_.size(), 0.0);
  deposits_.assign(particles_.size(), 0.0);
  // A caller's particles start at their own temperatures (not packing.initial_temperature).
  temperature_floor_ = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < particles_.size(); ++i) {
    total_volume_.add(particles_.volume(i));  // as volume_fractions sums its phases
    // A particle passed in dead left before this run: its temperature is no peak of the run's.
    if (particles_.alive[i])
      max_temperature_ = std::max(max_temperature_, particles_.temperature[i]);
    temperature_floor_ = std::min(temperature_floor_, particles_.temperature[i]);
  }
  for (const Wall& w : spec_.thermal.walls)
    temperature_floor_ = std::min(temperature_floor_, w.temperature);
  counts_.particles = particles_.size();
}

// The beam and its rays' energies in a pulse; returns a pulse's energy. A run without pulses draws
// no rays, only checks the beam's keys: at 10^7 rays the draw alone took 3 s and 0.45 GB.
double Simulation::set_up_beam() {
  if (builds_ray_scene(spec_)) {
    use_beam(make_beam(spec_.beam, spec_.packing.sample_size));
  } else {
    validate_beam(spec_.beam, spec_.packing.sample_size);
  }
  // With new rays per pulse, the first pulses' draws are checked now, as input.
  for (int k = 1; spec_.beam.resample && k < std::min(spec_.pulses.count, 64); ++k) {
    try {
      check_pulse_draw(spec_.beam, spec_.packing.sample_size, static_cast<std::uint64_t>(k));
    } catch (const InputError& e) {
      throw InputError("pulse " + std::to_string(k) + "'s rays (`beam.resample`): " + e.what());
    }
  }
  // Energies that overflow would turn into NaN at the first hit: refuse them as input.
  double pulse_energy = 0;
  for (double e : ray_energy_) pulse_energy += e;
  if (!std::isfinite(pulse_energy) || !std::isfinite(pulse_energy * spec_.pulses.count)) {
    std::ostringstream m;
    m << "`beam.power` = " << spec_.beam.power
      << " with `pulses.duration` = " << spec_.pulses.duration
      << " s: the pulse energy overflows double precision";
    throw InputError(m.str());
  }
  return pulse_energy;
}

void Simulation::set_up_tracer() {
  check_optics_tuning(spec_.optics);  // a value refused, though the chunk size is set here
  OpticsSpec optics = spec_.optics;
  optics.chunk_rays = spec_.dt > 0 ? 64 : 256;  // short budgets leave small chunks alone
  // The same rays every pulse: their first hits are reused (not with one pulse, or new rays each).
  optics.reuse_primaries =
      spec_.optics.reuse_primaries && spec_.pulses.count > 1 && !spec_.beam.resample;
  tracer_ = std::make_unique<Tracer>(particles_, optics);
  tracer_->keep_undo(spec_.max_staggers > 0);  // the stagger's redo takes a step back
  // The ray scene and bounce grid (~1 s at 10^6 particles) are built here, at set-up, for a run
  // that launches pulses; one without pulses never builds them.
  if (builds_ray_scene(spec_)) tracer_->build_scene();
}

// Leave out what the scene does not need: without conductivity or walls there is no graph, and
// without pulses no step that would conduct.
void Simulation::set_up_thermal() {
  thermal_ = std::make_unique<ThermalModel>(particles_, spec_.materials, spec_.thermal);
  if (builds_contact_graph(spec_)) {
    StageClock clock(stages_[kRebuild]);
    thermal_->set_contacts(find_contacts(particles_));
  }
}

Simulation::~Simulation() = default;

// A particle passed in dead is a vaporised one (README): its phase says so, in the figures and
// in particles.csv, whatever phase the caller left it with.
void Simulation::mark_dead_as_vapour() {
  for (std::size_t i = 0; i < particles_.size(); ++i)
    if (!particles_.alive[i]) particles_.phase[i] = Phase::vapor;
}

// The spec's own numbers, for library callers (the run file's ranges hold them for the CLI): a
// negative or NaN thermal.dt read as "pulse", a negative period or stagger cap ran without a word,
// and so did times beyond their caps (the quick scene's thermal.dt = 1e308 s to a clock of inf).
void Simulation::check_run_numbers() const {
  const auto refuse = [](const char* key, double value, const std::string& limit) {
    throw InputError(std::string("`") + key + "` = " + shown_number(value) + ": " + limit);
  };
  const PulseSpec& p = spec_.pulses;
  if (p.count < 0) refuse("pulses.count", p.count, "must be >= 0");
  if (!(p.duration > 0) || !std::isfinite(p.duration))  // a default spec's 0 says what "auto" is
    refuse("pulses.duration", p.duration,
           "must be > 0 and finite (the run file's \"auto\" is paper_time_step(xi, R), xi R / c: "
           "5.42e-15 s for the paper's scene)");
  if (p.duration > kDurationCap.limit)
    refuse("pulses.duration", p.duration, cap_limit(kDurationCap));
  if (!(p.period >= 0) || !std::isfinite(p.period))
    refuse("pulses.period", p.period, "must be >= 0 (0: each pulse when the last has ended)");
  if (p.period > kStepCap.limit) refuse("pulses.period", p.period, cap_limit(kStepCap));
  if (!(spec_.dt >= 0) || !std::isfinite(spec_.dt))
    refuse("thermal.dt", spec_.dt, "must be >= 0 (0: one step per pulse flight)");
  if (spec_.dt > kStepCap.limit) refuse("thermal.dt", spec_.dt, cap_limit(kStepCap));
  if (steps_per_crossing(spec_) > kMaxStepsPerCrossing)  // a run without end: 1e-30 s
    refuse("thermal.dt", spec_.dt, least_step_limit(spec_));
  if (spec_.max_staggers < 0) refuse("thermal.max_staggers", spec_.max_staggers, "must be >= 0");
}

// ", from `packing.radius_ratio` = 1e-300" when the spec's packing gave particle i its radius.
std::string Simulation::radius_origin(std::size_t i) const {
  const PackingSpec& p = spec_.packing;
  if (!packing_from_spec_) return "";
  const std::string setting = radius_setting(p);
  const double given = p.source == "file" ? p.file_radius : packing_radius(p);
  return !setting.empty() && particles_.radius[i] == given ? ", from " + setting : "";
}

// Every particle's thermal mass rho V C / M (M = thermal.time_scaling, as the solver uses it) must
// be a normal double, and the run's whole energy in it must warm it by a finite amount: otherwise
// the first solve gives infinities (density 1e-300, a radius of 1e-120 m, M = 1e300). Refused as
// input, naming the keys and the particle.
void Simulation::check_thermal_masses(double run_energy) const {
  for (std::size_t i = 0; i < particles_.size(); ++i) {
    const std::size_t k = particles_.material[i];
    if (k >= spec_.materials.size()) continue;  // the thermal model reports a missing material
    const Material& m = spec_.materials[k];
    const double mass_heat =
        least_thermal_mass(m, particles_.volume(i), spec_.thermal.time_scaling);
    if (mass_heat >= std::numeric_limits<double>::min() && std::isfinite(mass_heat) &&
        std::isfinite(run_energy / mass_heat))
      continue;
    const std::string key =
        spec_.materials.size() == 1 ? "material" : "material[" + std::to_string(k) + "]";
    std::ostringstream msg;
    msg << "particle " << i << " (radius " << particles_.radius[i] << " m" << radius_origin(i)
        << ") has a thermal mass `" << key << ".density` x volume x min(`" << key << ".c_solid`, `"
        << key << ".c_liquid`) / "
        << "`thermal.time_scaling` = " << m.density << " x " << particles_.volume(i) << " x "
        << std::min(m.c_solid, m.c_liquid) << " / " << spec_.thermal.time_scaling << " = "
        << mass_heat << " J/K: must be a finite normal number that the run's " << run_energy
        << " J warms by a finite amount";
    throw InputError(msg.str());
  }
}

// phi < 1 splits a step longer than its limit into sub-steps, up to thermal.max_substeps. The
// limit only grows during a run (vaporised particles take their contacts along; capacities are
// the lesser phase's), so steps the user fixed are checked here, as input: a fixed dt, and with
// one step per pulse flight the wait for the next pulse, up to pulses.period (a little less: the
// wait is the period less the flight, which is not known yet).
void Simulation::check_step_limit() const {
  std::ostringstream what;
  if (spec_.dt > 0) {
    what << "`thermal.dt` = " << spec_.dt << " s";
    check_substeps(spec_.dt, what.str());
  } else if (spec_.pulses.period > 0 && spec_.pulses.count > 1) {  // waits only between pulses
    what << "`pulses.period` = " << spec_.pulses.period << " s (with `thermal.dt` = \"pulse\" the "
         << "wait for the next pulse is one step)";
    check_substeps(spec_.pulses.period, what.str());
  }
}

// The thermal model's refusal of a step beyond thermal.max_substeps, naming what made the step.
void Simulation::check_substeps(double step, const std::string& made_by) const {
  try {
    thermal_->substep_count(step);
  } catch (const InputError& e) {
    throw InputError(made_by + ": " + e.what());
  }
}

bool Simulation::done() const {
  return launched_ >= spec_.pulses.count && !tracer_->has_live_rays();
}

bool Simulation::pulse_due() const {
  if (launched_ >= spec_.pulses.count) return false;
  return spec_.pulses.period > 0 ? time_ >= next_pulse_time_ * (1 - 1e-12)
                                 : !tracer_->has_live_rays();
}

// Every pulse due by this step boundary starts at it: with a step longer than the period several
// do (one per step let the delays grow with k without bound). "auto" starts one, whose rays are
// then live.
void Simulation::launch_due_pulses() {
  while (pulse_due()) launch_pulse();
}

// The caller's on_pulse_end, marked as running: it is called from inside a step, which a step()
// from it would re-enter (launching the same pulse and calling it again, until the stack ran out).
void Simulation::end_pulse(int pulse) {
  if (!on_pulse_end_) return;
  in_callback_ = true;
  struct Reset {
    bool& running;
    ~Reset() { running = false; }  // when the callback throws too
  } reset{in_callback_};
  try {
    on_pulse_end_(pulse);
  } catch (...) {
    callback_threw_ = true;  // at a pulse boundary, nothing of the step half done: step() may go on
    throw;
  }
}

void Simulation::launch_pulse() {
  if (launched_ > 0) end_pulse(launched_ - 1);
  if (spec_.beam.resample && launched_ > 0) use_beam(resampled_beam(launched_));
  {
    StageClock clock(stages_[kTrace], false);  // a launch traces the rays' first hits
    tracer_->compact();
    tracer_->launch(beam_, ray_energy_);
  }
  counts_.rays += beam_.size();
  note_pulse_delay(time_ - next_pulse_time_);
  ++launched_;
  // Pulse k is due at k T_p (MODEL.md section 5), however late the one before it started.
  next_pulse_time_ = launched_ * spec_.pulses.period;
}

namespace {

// A wall within whose reach no particle lies takes no heat: legal, but not what naming it asks.
void warn_of_walls_touching_nothing(const SimulationSpec& spec, const Particles& p,
                                    std::vector<std::string>& warnings) {
  for (const Wall& w : spec.thermal.walls) {
    std::size_t touching = 0;
    for (std::size_t i = 0; i < p.size(); ++i) touching += touches(w, p, i);
    if (touching > 0 || p.size() == 0) continue;
    warnings.push_back(std::string("the wall ") + "xyz"[w.axis] + (w.position > 0 ? '+' : '-') +
                       " (`thermal.walls`) touches no particle: none lies within "
                       "`thermal.wall_reach` = " +
                       shown_number(w.reach) + " m of it, so it takes no heat");
  }
}

// A beam whose tube meets no particle is legal but almost always a misplaced sample (a file
// packing whose coordinates lie outside the cube [0, D]^3 the beam is centred on): say so.
void warn_if_beam_meets_nothing(const SimulationSpec& spec, const Particles& p, const Beam& beam,
                                std::vector<std::string>& warnings) {
  if (p.size() == 0 || beam.size() == 0) return;  // no particles, or no pulses
  Vec3 lo = p.centre[0], hi = p.centre[0];
  for (std::size_t i = 0; i < p.size(); ++i) {
    const Vec3 off = p.centre[i] - beam.centre;
    const Vec3 across = off - off.dot(beam.direction) * beam.direction;
    if (across.norm() < beam.radius + p.radius[i]) return;
    lo = lo.cwiseMin(p.centre[i]), hi = hi.cwiseMax(p.centre[i]);
  }
  std::ostringstream m;
  const auto span = [&](int axis) {
    return " [" + shown_number(lo[axis]) + ", " + shown_number(hi[axis]) + "]";
  };
  m << "the beam (disk of radius " << shown_number(beam.radius) << " m centred at ("
    << shown_number(beam.centre.x()) << ", " << shown_number(beam.centre.y()) << ", "
    << shown_number(beam.centre.z()) << ") m on the face of the sample cube [0, "
    << shown_number(spec.packing.sample_size)
    << "]^3 m, `sample.size`) meets no particle: the particles' centres span x" << span(0) << ", y"
    << span(1) << ", z" << span(2) << " m";
  warnings.push_back(m.str());
}

// The beam is sized by sample.size (a disk of diameter_fraction D): on a packing file's particles
// it may be narrower than they are, and meet one or a few (a bed of 1 cm spheres with sample.size
// left at its 1 mm default), and so may a library caller's (whatever spec.packing.source says).
// Generated packings scale their radius with D: with ten particles or fewer they are wider than the
// beam by design, and nothing is said of them.
void warn_if_beam_narrower_than_particles(const SimulationSpec& spec, const Particles& p,
                                          bool generated, std::vector<std::string>& warnings) {
  if (spec.pulses.count == 0 || generated) return;
  std::vector<double> radii;
  for (std::size_t i = 0; i < p.size(); ++i)
    if (p.alive[i]) radii.push_back(p.radius[i]);
  if (radii.empty()) return;
  const auto mid = radii.begin() + std::ptrdiff_t(radii.size() / 2);
  std::nth_element(radii.begin(), mid, radii.end());
  const double width = spec.beam.diameter_fraction * spec.packing.sample_size;
  if (!(width < 2 * *mid)) return;
  warnings.push_back("the beam is " + shown_number(width) + " m wide (`beam.diameter_fraction` = " +
                     shown_number(spec.beam.diameter_fraction) +
                     " x `sample.size` = " + shown_number(spec.packing.sample_size) +
                     " m), narrower than the particles (median diameter " + shown_number(2 * *mid) +
                     " m): it meets one or a few of them; `sample.size` sizes the beam and the "
                     "cube [0, sample.size]^3 it is centred on: set it to the packing's extent");
}

// The widest empty slab between the particles along `axis` (no sphere reaches into it), found
// on a grid of bins over their extent: its width to within two bins, where it starts, and how
// many particles lie below it.
struct Gap {
  double width = 0, from = 0;
  std::size_t below = 0;
};

Gap widest_gap(const Particles& p, int axis, double lo, double hi) {
  const std::size_t bins = std::min<std::size_t>(4096, 4 * p.alive_count());
  const double w = (hi - lo) / static_cast<double>(bins);
  std::vector<int> starts(bins + 1, 0);  // spheres whose extent begins minus those that ended
  const auto bin = [&](double x) {
    return std::min(bins - 1, static_cast<std::size_t>(std::max(0.0, (x - lo) / w)));
  };
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (!p.alive[i]) continue;
    ++starts[bin(p.centre[i][axis] - p.radius[i])];
    --starts[bin(p.centre[i][axis] + p.radius[i]) + 1];
  }
  Gap widest;
  std::size_t run = 0;
  int covering = 0;
  for (std::size_t b = 0; b < bins; ++b) {
    covering += starts[b];
    run = covering > 0 ? 0 : run + 1;
    if (covering == 0 && static_cast<double>(run) * w > widest.width)
      widest = {static_cast<double>(run) * w, lo + static_cast<double>(b + 1 - run) * w, 0};
  }
  for (std::size_t i = 0; i < p.size(); ++i)
    widest.below += p.alive[i] && p.centre[i][axis] < widest.from;
  return widest;
}

// A ray ends when it leaves the bounding box of all particles (MODEL.md section 3): one stray
// particle far from the rest (a DEM particle that flew off, a row in other units) stretches it,
// and with it every pulse's flight, the "pulse" step and the "auto" period (a library review: a
// 10 um sphere 1 m from a 1 mm bed took its peak from 624 K to 323 K without a word). Said when
// an empty slab between the particles is wider than the rest of their extent along that axis
// and than four of the largest diameters. Generated packings fill their cube.
void warn_of_particles_far_apart(const SimulationSpec& spec, const Particles& p, bool generated,
                                 std::vector<std::string>& warnings) {
  if (spec.pulses.count == 0 || generated || p.alive_count() < 2) return;
  const Box box = p.bounds();
  double largest = 0;
  for (std::size_t i = 0; i < p.size(); ++i)
    if (p.alive[i]) largest = std::max(largest, p.radius[i]);
  for (int axis = 0; axis < 3; ++axis) {
    const double span = box.upper[axis] - box.lower[axis];
    const Gap gap = widest_gap(p, axis, box.lower[axis], box.upper[axis]);
    if (!(gap.width > span - gap.width && gap.width > 8 * largest)) continue;
    const std::size_t above = p.alive_count() - gap.below;
    warnings.push_back(
        "the particles lie in two groups far apart: along " + std::string(1, "xyz"[axis]) +
        " an empty gap of " + shown_number(gap.width) + " m (from " + shown_number(gap.from) +
        " m) separates " + std::to_string(gap.below) + " of them from " + std::to_string(above) +
        ", and they span " + shown_number(span) +
        " m; a ray ends only when it leaves the particles' bounding box, so each pulse's flight, "
        "the \"pulse\" step and the \"auto\" period grow with the gap (a stray particle, or a row "
        "in other units?)");
    return;
  }
}

// Without particles every ray escapes at once: a pulse's flight is 0, so with the automatic
// period and one step per flight no step has a length and time stays 0 in history.csv.
void warn_if_time_stands_still(const SimulationSpec& spec, const Particles& p,
                               std::vector<std::string>& warnings) {
  if (spec.dt > 0 || spec.pulses.period > 0 || spec.pulses.count == 0) return;
  if (p.alive_count() > 0) return;
  warnings.push_back(
      "no particles: every ray escapes at once, so with `pulses.period` = \"auto\" and "
      "`thermal.dt` = \"pulse\" no step has a length and time stays 0; set `pulses.period` (s) "
      "or `thermal.dt` (s) for a time axis");
}

}  // namespace

std::vector<std::string> Simulation::scene_warnings() const {
  std::vector<std::string> warnings;
  warn_if_beam_meets_nothing(spec_, particles_, beam_, warnings);
  warn_if_beam_narrower_than_particles(spec_, particles_, generated_packing(), warnings);
  warn_of_walls_touching_nothing(spec_, particles_, warnings);
  warn_if_time_stands_still(spec_, particles_, warnings);
  warn_of_particles_far_apart(spec_, particles_, generated_packing(), warnings);
  return warnings;
}

// The beam of the pulses from now on, with its rays' energies in a pulse.
void Simulation::use_beam(Beam beam) {
  beam_ = std::move(beam);
  ray_energy_ = beam_.ray_energies(spec_.pulses.duration);
}

// Pulse k's own rays (beam.resample). A draw whose rays all miss a profile too narrow to
// sample (the first pulses are checked as input when the run is set up) stops the run.
Beam Simulation::resampled_beam(int pulse) const {
  try {
    return make_beam(spec_.beam, spec_.packing.sample_size, static_cast<std::uint64_t>(pulse));
  } catch (const InputError& e) {
    throw RunError("pulse " + std::to_string(pulse) + " (`beam.resample`): " + e.what());
  }
}

// The thermal step (3.10). With one step per pulse flight a step's length is the rays' (or the
// wait for the next pulse), which the user did not write as thermal.dt: a refusal says so.
StepReport Simulation::heat_step(double dt) {
  if (!(spec_.dt > 0))
    check_substeps(dt, "`thermal.dt` = \"pulse\" (step " + std::to_string(counts_.steps) +
                           " lasts the rays' flight, or the wait for the next pulse)");
  return thermal_->step(dt, deposits_, heated_);
}

// A pulse starts at a step boundary: with thermal.dt = "pulse" a step is a whole flight, so a
// T_p shorter than the flight delays every pulse to the end of the one before.
void Simulation::note_pulse_delay(double delay) {
  if (!(spec_.pulses.period > 0)) return;
  if (delay > 0.01 * spec_.pulses.period) ++counts_.late_pulses;
  counts_.max_pulse_delay = std::max(counts_.max_pulse_delay, delay);
}

// The step's length: the user's dt; in "pulse" mode (dt = 0) the flight of the rays traced to
// their end in this step, or the wait until the next pulse when no ray was live.
double Simulation::step_length(bool traced) const {
  if (spec_.dt > 0) return spec_.dt;
  if (traced) return tracer_->last_advance_path() / kSpeedOfLight;
  return std::max(next_pulse_time_ - time_, 0.0);
}

bool Simulation::step() {
  if (in_callback_)
    throw InputError(
        "step: called from inside this simulation's on_pulse_end callback, which runs in the "
        "middle of a step (run() steps too): a simulation cannot be stepped from its own "
        "callback; step it after the callback returns");
  if (failed_)
    throw RunError("step: an earlier step failed (" + failed_step_ +
                   "), leaving its rays traced and its heat not: this simulation cannot go on; "
                   "restore a state saved before it into a new one");
  if (done()) return false;
  try {
    return take_step();
  } catch (const std::exception& e) {
    if (std::exchange(callback_threw_, false)) throw;  // the caller's own error: not a failed step
    failed_ = true;
    failed_step_ = e.what();
    throw;
  } catch (...) {
    if (std::exchange(callback_threw_, false)) throw;
    failed_ = true;
    failed_step_ = "an exception of a type not derived from std::exception";
    throw;
  }
}

// One time step of MODEL.md section 5, its stages in the physics' order.
bool Simulation::take_step() {
  if constexpr (BEAMPACK_CHECKS_ON) name_step_for_checks();
  launch_due_pulses();
  const double budget =
      spec_.dt > 0 ? kSpeedOfLight * spec_.dt : std::numeric_limits<double>::infinity();
  tracer_->compact_if_sparse();  // ended rays would be scanned by every chunk that runs
  // Trace, heat and phases, redone while a phase change alters the optics the rays met.
  const StepOutcome step = trace_and_heat(budget);
  book_step(step);
  // Numerical hygiene: a NaN or infinity stops the run here, before it reaches any output.
  check_finite_and_note_peak();
  // Rebuild: vaporised particles leave the scene and the contact graph (paper, Remark 10).
  if (!step.report.vaporized.empty()) remove_vaporized(step.report.vaporized);
  if constexpr (BEAMPACK_CHECKS_ON) check_ledgers_close();
  // Output: the last pulse ends with the run (the others end as the next one starts).
  if (done()) end_pulse(launched_ - 1);
  return !done();
}

// Trace (every live ray advances by at most `budget` of path, depositing into dH), then the
// implicit step (3.10) with dH and the latent-heat bands (section 4); then the stagger: a phase
// change that alters the optics of a particle the rays met sends the step back to the trace,
// with the new indices (bounded number of times). Redos that would only alternate between two
// sets of phases (a particle melts when traced solid and stays solid when traced liquid) stop at
// the second pass of the cycle, whatever the cap.
Simulation::StepOutcome Simulation::trace_and_heat(double budget) {
  PhaseOverride seen;         // where the phases the rays see differ from the particles' (a redo)
  PhaseOverride seen_before;  // the pass before's
  StepOutcome out;
  for (int pass = 0;; ++pass) {
    for (std::uint32_t i : heated_) deposits_[i] = 0.0;
    heated_.clear();
    const bool traced = tracer_->has_live_rays();
    if (traced) {
      StageClock clock(stages_[kTrace]);
      swap_phases(seen);
      tracer_->advance(budget, deposits_, &heated_);
      out.chunks_run = tracer_->last_chunks_run(), out.chunks_live = tracer_->last_chunks_live();
      swap_phases(seen);
    }
    out.dt = step_length(traced);
    refuse_heat_without_time(out.dt);
    if (out.dt > 0 && particles_.size() > 0) out.report = heat_and_phases(out.dt);
    if (!optics_changed(seen)) break;
    PhaseOverride next = optics_after_step();
    const bool cycle = pass > 0 && next == seen_before;
    if (cycle || pass >= spec_.max_staggers) {
      ++(cycle ? counts_.stagger_cycles : counts_.capped_stagger_steps);
      if (cycle) counts_.stagger_cycle_particles += particles_differing(seen, next);
      break;
    }
    StageClock clock(stages_[kStagger]);
    ++counts_.staggers;
    seen_before = std::move(seen);
    seen = std::move(next);
    if (traced) tracer_->undo_advance();  // its recorded segments too: the redo records its own
    thermal_->undo_step();
    out.report = StepReport{};
  }
  return out;
}

// A step of no length cannot take the heat its trace deposited: it would leave the ledger.
void Simulation::refuse_heat_without_time(double dt) const {
  if (dt > 0 || std::none_of(heated_.begin(), heated_.end(),
                             [&](std::uint32_t i) { return deposits_[i] > 0; }))
    return;
  throw RunError("step " + std::to_string(counts_.steps) +
                 ": rays deposited energy in a step of "
                 "length 0 (the rays travelled no path); please report the run file");
}

// The heat step and, inside it, the latent-heat work, whose time is the phases stage's.
StepReport Simulation::heat_and_phases(double dt) {
  StepReport report;
  {
    StageClock clock(stages_[kHeat]);
    report = heat_step(dt);
  }
  stages_[kHeat].seconds -= report.phases_seconds;
  stages_[kPhases].seconds += report.phases_seconds;
  if (report.phases_ran) ++stages_[kPhases].calls;
  return report;
}

// The step's deposits, ray paths, counts and clock.
void Simulation::book_step(const StepOutcome& step) {
  for (std::uint32_t i : heated_) absorbed_[i] += deposits_[i];
  for (RaySegment& seg : tracer_->take_segments()) ray_paths_.push_back(seg);
  ++counts_.steps;
  // Fixed steps: the clock is n dt, rounded once. As a running sum its round-off grew with the
  // steps, past the due test's slack after ~1e4 steps a period: a pulse due on a step boundary
  // started one step late.
  time_ = spec_.dt > 0 ? static_cast<double>(counts_.steps) * spec_.dt : time_ + step.dt;
  counts_.heat_rows_solved += step.report.solved_rows;
  counts_.capped_phase_steps += step.report.phase_passes_capped;
  counts_.bands_short += step.report.bands_short;
  counts_.band_heat_short += step.report.band_heat_short;
  counts_.iterative_heat_steps += step.report.iterations > 0;
  counts_.heat_rows_live += step.report.live_rows;
  counts_.ray_chunks_run += step.chunks_run;
  counts_.ray_chunks_live += step.chunks_live;
}

// Only the particles the heat step changed can have new temperatures.
void Simulation::check_finite_and_note_peak() {
  for (std::uint32_t i : heated_)
    if (!std::isfinite(deposits_[i])) non_finite(i, particles_.temperature[i], deposits_[i]);
  double peak = max_temperature_;
  thermal_->for_each_changed([&](std::size_t i) {
    const double t = particles_.temperature[i];
    if (!std::isfinite(t)) non_finite(i, t, deposits_[i]);
    peak = std::max(peak, t);
  });
  max_temperature_ = peak;
}

// What a failed check (geometry/check.h) prints to say how to reproduce it.
void Simulation::name_step_for_checks() const {
  set_check_context(
      check_facts("step %llu (t = %.17g s, pulse %d) of a run of %zu particles, packing.seed %llu, "
                  "beam.seed %llu",
                  static_cast<unsigned long long>(counts_.steps), time_, launched_,
                  particles_.size(), static_cast<unsigned long long>(spec_.packing.seed),
                  static_cast<unsigned long long>(spec_.beam.seed)));
}

// After every step, in BEAMPACK_CHECKS builds: the optics ledger closes to round-off (it does by
// construction), the heat ledger to the solver's tolerance over every joule it books (a sum of
// magnitudes, looser than the end of a run's heat_error(), which warns instead of stopping).
void Simulation::check_ledgers_close() const {
  const EnergyLedger e = figures().energy;
  BEAMPACK_DCHECK(std::abs(e.optics_imbalance()) <= EnergyLedger::kOpticsTolerance * e.injected,
                  "optics ledger open by %g J of %g J injected", e.optics_imbalance(), e.injected);
  const double scale = e.absorbed + std::abs(e.stored) + e.vaporized + std::abs(e.walls);
  // A faint step's warming can lie below the temperatures' last digits: the ledger then opens by
  // their round-off, a limit of doubles that the run reports, not a bug.
  double heat_content = 0;
  for (std::size_t i = 0; i < particles_.size(); ++i)
    if (particles_.alive[i]) heat_content += thermal_->thermal_mass(i) * particles_.temperature[i];
  const double roundoff = 1e-12 * heat_content * double(counts_.steps);
  BEAMPACK_DCHECK(std::abs(e.heat_imbalance()) <=
                      EnergyLedger::heat_tolerance(spec_.thermal.tolerance) * scale + roundoff,
                  "heat ledger open by %g J (absorbed %g, stored %g, vaporised %g, walls %g J)",
                  e.heat_imbalance(), e.absorbed, e.stored, e.vaporized, e.walls);
}

// The phase whose index the rays see: a particle that vaporised in this step is still hit during
// it, as liquid (it leaves the scene from the next step, the paper's Remark 10).
Phase Simulation::optical(Phase phase) {
  return phase == Phase::vapor ? Phase::liquid : phase;
}

namespace {
// PhaseOverride entries ordered by particle.
bool by_particle(const std::pair<std::uint32_t, Phase>& a,
                 const std::pair<std::uint32_t, Phase>& b) {
  return a.first < b.first;
}
}  // namespace

// Whether a particle the rays met in this step ends it with another index than the trace used:
// solid <-> liquid, and solid -> vapour (which passed through liquid). The trace saw the phases
// before the step, except where `seen` says otherwise (a redo); so one the redo saw as liquid
// that ends solid counts too.
bool Simulation::optics_changed(const PhaseOverride& seen) const {
  for (std::uint32_t i : heated_) {
    if (!(deposits_[i] > 0)) continue;
    const auto it =
        std::lower_bound(seen.begin(), seen.end(), std::pair{i, Phase::solid}, by_particle);
    const Phase traced_as =
        it != seen.end() && it->first == i ? it->second : thermal_->phase_before_step(i);
    if (optical(particles_.phase[i]) != traced_as) return true;
  }
  return false;
}

// What a redo's rays see: the phases this step ended with (optical), where they differ from those
// before it. Only the particles the step changed can differ, so a redo costs what the step did.
Simulation::PhaseOverride Simulation::optics_after_step() const {
  PhaseOverride after;
  thermal_->for_each_changed([&](std::size_t i) {
    const Phase p = optical(particles_.phase[i]);
    if (p != thermal_->phase_before_step(i)) after.emplace_back(static_cast<std::uint32_t>(i), p);
  });
  std::sort(after.begin(), after.end(), by_particle);
  after.erase(std::unique(after.begin(), after.end(),
                          [](const auto& a, const auto& b) { return a.first == b.first; }),
              after.end());
  return after;
}

// The particles two overrides (sorted by particle) give different phases, or one gives and the
// other does not.
std::size_t Simulation::particles_differing(const PhaseOverride& a, const PhaseOverride& b) {
  std::size_t differing = 0, i = 0, j = 0;
  while (i < a.size() || j < b.size()) {
    if (j == b.size() || (i < a.size() && a[i].first < b[j].first)) ++differing, ++i;
    else if (i == a.size() || b[j].first < a[i].first) ++differing, ++j;
    else differing += a[i++].second != b[j++].second;
  }
  return differing;
}

// Puts the phases of `seen` on the particles and theirs into `seen`: twice is no change.
void Simulation::swap_phases(PhaseOverride& seen) {
  for (auto& [i, phase] : seen) std::swap(particles_.phase[i], phase);
}

void Simulation::non_finite(std::size_t particle, double temperature, double deposit) const {
  std::ostringstream m;
  m << "non-finite value at step " << counts_.steps << " (t = " << time_ << " s, pulse "
    << launched_ << "): particle " << particle << " has temperature " << temperature
    << " K and absorbed " << deposit << " J in the step; reproduce with the same run file "
    << "(packing.seed = " << spec_.packing.seed << ", beam.seed = " << spec_.beam.seed
    << ") and stop at that step";
  throw RunError(m.str());
}

void Simulation::remove_vaporized(const std::vector<std::uint32_t>& ids) {
  StageClock clock(stages_[kRebuild]);
  ++counts_.rebuilds;
  tracer_->remove_particles(ids);
  if (needs_conduction(spec_)) thermal_->drop_removed_contacts();
}

void Simulation::run(const std::atomic<bool>* stop) {
  while (!done() && !(stop && stop->load())) step();
}

std::array<StageTime, Simulation::kStages> Simulation::stages() const {
  std::array<StageTime, kStages> out = stages_;
  for (int k = 0; k < kStages; ++k)
    if (out[k].calls == 0) out[k].skipped_because = skip_reason(k);
  return out;
}

// Why stage k has not run so far: the condition under which the loop of step() leaves it out.
std::string Simulation::skip_reason(int stage) const {
  if (stage == kRebuild && needs_conduction(spec_) && !builds_contact_graph(spec_))
    return "`pulses.count` = 0: no pulse, no contact graph built";
  if (stage == kRebuild)
    return "no contact graph (no conductivity, no walls) and no particle vaporised";
  if (launched_ == 0 && spec_.pulses.count > 0) return "no step taken yet";
  if (launched_ == 0) {
    const bool unbuilt = stage == kTrace && !tracer_->has_scene();
    return unbuilt ? "`pulses.count` = 0: no pulse, no ray scene or bounce grid built"
                   : "`pulses.count` = 0: no pulse";
  }
  if (stage == kTrace) return "no ray was live in any step";
  if (particles_.size() == 0) return "no particles";  // heat, phases and stagger have none to do
  if (stage == kHeat) return "no step had a positive length";
  if (stage == kPhases)
    return "no particle whose temperature changed was at the melting temperature";
  if (spec_.max_staggers == 0) return "`thermal.max_staggers` = 0";
  return "no phase change altered the optics of a particle the rays met";
}

// The vaporised and melted volume fractions in one pass over the particles (figures() runs at
// every pulse end). Each is a compensated sum of its phase's volumes in particle order: a plain
// sum of 10^6 volumes drifts by ~1e-13, and equal spheres' fractions showed it
// (0.029999999999999884 for 6 of 200).
void Simulation::volume_fractions(Figures& f) const {
  if (total_volume_.value() <= 0) return;
  CompensatedSum vapor, liquid;
  for (std::size_t i = 0; i < particles_.size(); ++i) {
    const Phase phase = particles_.phase[i];
    if (phase == Phase::vapor) vapor.add(particles_.volume(i));
    else if (phase == Phase::liquid) liquid.add(particles_.volume(i));
  }
  f.vaporized_fraction = compensated_ratio(vapor, total_volume_);
  f.melted_fraction = compensated_ratio(liquid, total_volume_);
}

Figures Simulation::figures() const {
  Figures f;
  f.time = time_;
  f.pulse = launched_;
  volume_fractions(f);
  if (max_temperature_ > 0) f.max_temperature = max_temperature_;  // temperatures are > 0 K
  f.particles = particles_.size();
  const OpticsLedger& o = tracer_->ledger();
  const ThermalLedger& h = thermal_->ledger();
  f.energy = {o.injected, o.absorbed,  o.escaped, o.cutoff, tracer_->energy_in_flight(),
              h.stored,   h.vaporized, h.walls};
  return f;
}

void Simulation::write_state(StateWriter& out) const {
  if (failed_)  // half-stepped or half-restored: no state to go on from
    throw RunError("write_state: this simulation failed (" + failed_step_ +
                   "): it holds no state to save; save one before the failure");
  out.value(kStateFormat);
  const Particles& p = particles_;
  out.vector(p.centre), out.vector(p.radius), out.vector(p.material);
  out.vector(p.temperature), out.vector(p.phase), out.vector(p.alive);
  out.vector(absorbed_);
  out.value(time_), out.value(next_pulse_time_), out.value(max_temperature_), out.value(launched_);
  out.value(counts_);
  for (const StageTime& s : stages_) out.value(s.seconds), out.value(s.calls);
  tracer_->save().write(out);
  tracer_->write_first_hits(out);
  const ThermalModel::Snapshot heat = thermal_->save();
  out.vector(heat.stored);
  out.value(heat.ledger);
  out.value(heat.reference);
  out.vector(ray_paths_);
}

// What a checkpoint holds, read whole before the simulation changes.
struct SavedRun {
  Particles particles;
  std::vector<double> absorbed;
  double time = 0, next_pulse_time = 0, max_temperature = 0;
  int launched = 0;
  Counts counts;
  std::array<StageTime, Simulation::kStages> stages{};
  RayState rays;
  Tracer::FirstHits first_hits;
  ThermalModel::Snapshot heat;
  std::vector<RaySegment> ray_paths;
};

namespace {

void require_in_state(bool ok, const std::string& what) {
  if (!ok) throw InputError("checkpoint: " + what);
}

void require_material(std::size_t particle, std::uint16_t material, const SimulationSpec& spec) {
  require_in_state(material < spec.materials.size(),
                   "particle " + std::to_string(particle) + " has material " +
                       std::to_string(material) + " of " + std::to_string(spec.materials.size()));
}

// A checksum guards the bytes, not a writer's mistake or an edit: every value must be one a run
// can hold (a particle index past the arrays crashed the tracer, a NaN reached the outputs).
void check_saved_values(const SavedRun& s, const SimulationSpec& spec) {
  require_in_state(std::isfinite(s.time) && s.time >= 0 && std::isfinite(s.next_pulse_time) &&
                       s.next_pulse_time >= 0 && !std::isnan(s.max_temperature),
                   "its time, next pulse time or peak temperature is not a number a run reaches");
  const Particles& p = s.particles;
  for (std::size_t i = 0; i < p.size(); ++i) {
    const std::string particle = "particle " + std::to_string(i) + " has ";
    require_material(i, p.material[i], spec);
    require_in_state(std::isfinite(p.temperature[i]) && p.temperature[i] >= 0,
                     particle + "temperature " + std::to_string(p.temperature[i]) + " K");
    require_in_state(p.phase[i] <= Phase::vapor && p.alive[i] <= 1,
                     particle + "a phase or live flag out of range");
    // A run removes a particle exactly when it vaporises (mark_dead_as_vapour, remove_vaporized).
    require_in_state(
        (p.alive[i] == 1) == (p.phase[i] != Phase::vapor),
        particle + (p.alive[i] ? "phase vapor and is live" : "been removed unvaporised"));
    // A live particle at theta_v had vaporised: a state of a spec with a higher theta_v (a
    // library caller's; the command line refuses --set on a resume) left it live above.
    const Material& m = spec.materials[p.material[i]];
    require_in_state(!p.alive[i] || p.temperature[i] < m.vapor_temperature,
                     particle + "temperature " + shown_number(p.temperature[i]) +
                         " K and is live, at or above its material's vapor_temperature " +
                         shown_number(m.vapor_temperature) + " K (a state of another spec?)");
    require_in_state(p.temperature[i] <= s.max_temperature,
                     particle + "temperature " + std::to_string(p.temperature[i]) +
                         " K, above the run's peak " + std::to_string(s.max_temperature) + " K");
    require_in_state(std::isfinite(s.absorbed[i]) && s.absorbed[i] >= 0,
                     particle + "absorbed " + std::to_string(s.absorbed[i]) + " J");
    require_in_state(std::isfinite(s.heat.stored[i]),
                     particle + "stored heat " + std::to_string(s.heat.stored[i]) + " J");
  }
  require_in_state(s.launched >= 0 && s.launched <= spec.pulses.count,
                   std::to_string(s.launched) +
                       " pulses launched, of pulses.count = " + std::to_string(spec.pulses.count));
  // Pulse k is due at k T_p (launch_pulse): one edited to 1e300 s was waited for without end.
  require_in_state(s.next_pulse_time == s.launched * spec.pulses.period,
                   "next pulse time " + shown_number(s.next_pulse_time) + " s after " +
                       std::to_string(s.launched) + " pulses of period " +
                       shown_number(spec.pulses.period) + " s");
  require_in_state(std::isfinite(s.counts.max_pulse_delay) && s.counts.max_pulse_delay >= 0,
                   "its longest pulse delay is " + shown_number(s.counts.max_pulse_delay) + " s");
  require_in_state(std::isfinite(s.counts.band_heat_short) && s.counts.band_heat_short >= 0,
                   "its latent heat charged short of a crossing is " +
                       shown_number(s.counts.band_heat_short) + " J");
  // Rays come only from a launch: live rays before any would be traced, and heated without the
  // contact graph a spec without pulses does not build.
  require_in_state(s.launched > 0 || s.rays.live_count == 0,
                   std::to_string(s.rays.live_count) + " live rays and no pulse launched");
  require_in_state(s.counts.particles == p.size(),
                   "its counts are of " + std::to_string(s.counts.particles) + " particles");
  const ThermalLedger& h = s.heat.ledger;
  for (const double v : {h.absorbed, h.stored, h.vaporized, h.walls})
    require_in_state(std::isfinite(v), "a heat ledger entry is " + std::to_string(v));
  require_in_state(
      std::isfinite(s.heat.reference) && s.heat.reference >= 0,
      "its heat solve's reference temperature is " + std::to_string(s.heat.reference) + " K");
  for (const StageTime& t : s.stages)
    require_in_state(std::isfinite(t.seconds) && t.seconds >= 0, "a stage time is not finite");
  s.rays.check_values(p.size(), "checkpoint");
  for (const RaySegment& r : s.ray_paths)
    require_in_state(
        r.from.allFinite() && r.to.allFinite() && std::isfinite(r.energy) && r.energy >= 0,
        "a recorded ray path holds a value that is not a finite number");
}

// A state begins with its format's version: another's fields would be read as this one's.
void read_state_version(StateReader& in) {
  if (in.value<std::uint32_t>() != kStateFormat)
    throw InputError("checkpoint: written by another version of beampack's state format");
}

// A checkpoint's state, read whole and checked against the simulation's own packing (`current`)
// before the simulation changes; the tracer reads its part.
SavedRun read_saved_run(StateReader& in, Tracer& tracer, const Particles& current) {
  read_state_version(in);
  SavedRun s;
  Particles& p = s.particles;
  in.vector(p.centre), in.vector(p.radius), in.vector(p.material);
  in.vector(p.temperature), in.vector(p.phase), in.vector(p.alive);
  if (p.size() != current.size() || p.centre.size() != p.size())
    throw InputError("checkpoint: its packing has " + std::to_string(p.size()) +
                     " particles, this simulation's (the run file's) " +
                     std::to_string(current.size()));
  in.vector(s.absorbed);
  s.time = in.value<double>(), s.next_pulse_time = in.value<double>();
  s.max_temperature = in.value<double>(), s.launched = in.value<int>();
  s.counts = in.value<Counts>();
  for (StageTime& t : s.stages) t.seconds = in.value<double>(), t.calls = in.value<std::uint64_t>();
  s.rays.read(in);
  s.first_hits = tracer.read_first_hits(in);
  in.vector(s.heat.stored);
  s.heat.ledger = in.value<ThermalLedger>();
  s.heat.reference = in.value<double>();
  in.vector(s.ray_paths);
  // The geometry must be the run file's: the scene, the grid and the contact graph were built
  // from it.
  if (p.centre != current.centre || p.radius != current.radius)
    throw InputError(
        "checkpoint: its packing differs from this simulation's (the run file's: other seed or "
        "file?)");
  // A checksum guards the bytes, not a writer's mistake: every per-particle array must fit.
  const std::size_t n = p.size();
  for (std::size_t size : {p.material.size(), p.temperature.size(), p.phase.size(), p.alive.size(),
                           s.absorbed.size(), s.heat.stored.size()})
    if (size != n)
      throw InputError("checkpoint: a per-particle array holds " + std::to_string(size) +
                       " values for " + std::to_string(n) + " particles");
  return s;
}

}  // namespace

Particles Simulation::saved_packing(StateReader in, const SimulationSpec& spec) {
  read_state_version(in);
  Particles saved;
  in.vector(saved.centre), in.vector(saved.radius), in.vector(saved.material);
  if (saved.centre.size() != saved.radius.size() || saved.material.size() != saved.radius.size())
    throw InputError("checkpoint: its packing's arrays differ in length");
  Particles p;
  p.reserve(saved.radius.size());
  for (std::size_t i = 0; i < saved.radius.size(); ++i) {
    // The checks a packing file's rows pass: the scene and the grid are built from these.
    check_sphere(saved.centre[i], saved.radius[i], {0, 1, 2},
                 "checkpoint: particle " + std::to_string(i) + ": ");
    require_material(i, saved.material[i], spec);
    p.add(saved.centre[i], saved.radius[i], saved.material[i], spec.packing.initial_temperature);
  }
  return p;
}

void Simulation::read_state(StateReader& in) {
  // The particles a run removed are gone from its ray scene and contact graph for good: a state
  // that has them alive would be traced through them.
  if (counts_.steps > 0 || launched_ > 0)
    throw InputError("checkpoint: this simulation has taken " + std::to_string(counts_.steps) +
                     " steps: restore a state into a new Simulation built from the same spec");
  SavedRun s = read_saved_run(in, *tracer_, particles_);
  check_saved_values(s, spec_);
  tracer_->check_restorable(s.rays, "checkpoint");
  // Every check is behind: what throws below (no memory for the ray scene's rebuild) leaves the
  // simulation part restored, and step() refuses to go on from there.
  try {
    restore_saved_run(s);
  } catch (const std::exception& e) {
    failed_ = true;
    failed_step_ = std::string("restoring a state: ") + e.what();
    throw;
  }
}

// The state arrays are copied into place: the tracer and the heat model keep their references to
// particles_.
void Simulation::restore_saved_run(SavedRun& s) {
  time_ = s.time, next_pulse_time_ = s.next_pulse_time, max_temperature_ = s.max_temperature;
  launched_ = s.launched, counts_ = s.counts;
  for (int k = 0; k < kStages; ++k)
    stages_[k].seconds = s.stages[k].seconds, stages_[k].calls = s.stages[k].calls;
  absorbed_ = std::move(s.absorbed);
  ray_paths_ = std::move(s.ray_paths);
  const Particles& p = s.particles;
  std::copy(p.material.begin(), p.material.end(), particles_.material.begin());
  std::copy(p.temperature.begin(), p.temperature.end(), particles_.temperature.begin());
  std::copy(p.phase.begin(), p.phase.end(), particles_.phase.begin());
  std::copy(p.alive.begin(), p.alive.end(), particles_.alive.begin());
  std::vector<std::uint32_t> dead;
  for (std::uint32_t i = 0; i < particles_.size(); ++i)
    if (!particles_.alive[i]) dead.push_back(i);
  tracer_->remove_particles(dead);
  tracer_->restore(s.rays);
  tracer_->restore_first_hits(std::move(s.first_hits));
  ThermalModel::Snapshot& heat = s.heat;
  heat.temperature = particles_.temperature;
  heat.phase = particles_.phase;
  heat.alive = particles_.alive;
  thermal_->restore(heat);
  if (needs_conduction(spec_)) thermal_->drop_removed_contacts();
}

Counts Simulation::counts() const {
  Counts c = counts_;
  c.segments = tracer_->primary_segments() + tracer_->bounced_segments();
  c.primaries_reused = tracer_->reused_primaries();
  return c;
}

}  // namespace beampack
