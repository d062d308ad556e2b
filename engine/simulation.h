#pragma once
// The simulator as a library: the staggered loop of MODEL.md section 5 over a packing, a beam,
// the optics and the heat. Build a SimulationSpec (or a Particles set) in code, run pulses, read
// temperatures: see examples/run_in_code.cpp.
#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "../geometry/compensated_sum.h"
#include "../geometry/error.h"
#include "../geometry/packing.h"
#include "../thermal/thermal_model.h"
#include "beam.h"
#include "state_io.h"
#include "tracer.h"

namespace beampack {

constexpr double kSpeedOfLight = 2.99792458e8;  // m/s

// The paper's ray time step xi R / c (MODEL.md sections 2 and 5; xi = 0.05..0.1): the
// duration of a pulse by default (`pulses.duration = "auto"`), and thermal.dt = "paper".
constexpr double paper_time_step(double xi, double radius) {
  return xi * radius / kSpeedOfLight;
}

// The limits of a run's times, physically generous, beyond which its arithmetic breaks:
// thermal.dt = 1e308 s with K = 1e4 gave non-finite temperatures, pulses.period = 1e308 s
// "thermal.dt = inf", and conjugate gradients' residual turned NaN at pulses.duration = 1e290 s.
inline constexpr Cap kDurationCap{
    1e12,
    "s (30,000 years; far longer pulses overflow their energy and the temperatures it "
    "gives)"};
// More steps than this per light crossing of the sample (a fixed thermal.dt) would never finish
// (a typo of the exponent, most likely); the paper's dt takes thousands.
inline constexpr double kMaxStepsPerCrossing = 1e9;
// thermal.dt, and pulses.period: with thermal.dt = "pulse" the wait for the next pulse is one step.
inline constexpr Cap kStepCap{
    1e12,
    "s (30,000 years; far longer steps overflow their heat flows, time step times "
    "conductance times temperature)"};

struct PulseSpec {
  int count = 20;  // pulses.count
  // tau, s: E_k = I_k A_r tau, delivered within the rays' flight, not over tau (MODEL.md section
  // 5). Required, > 0 and at most kDurationCap: the run file's "auto" is paper_time_step(xi, R).
  double duration = 0;
  double period = 0;  // s between pulse starts; 0: "auto", when the previous pulse has ended;
                      // at most kStepCap
};

struct SimulationSpec {
  PackingSpec packing;
  BeamSpec beam;
  OpticsSpec optics;
  // Material ids index both this and optics.materials (the indices): two materials need both
  // resized. Messages name run-file keys (INTERFACE.md), whose fields are noted beside them.
  std::vector<Material> materials{Material{}};
  ThermalSpec thermal;
  PulseSpec pulses;
  double dt = 0;         // thermal.dt, s; 0: one step per pulse flight ("pulse"); <= kStepCap
  int max_staggers = 4;  // redo a step at most this often when a phase change alters optics
};

// Whether the scene conducts heat (a material's conductivity, or walls): only then are the
// contacts found and the conduction system kept.
bool needs_conduction(const SimulationSpec& spec);
// Whether a material's conductivity is > 0: heat flows between particles, not only to walls.
bool conducts_between_particles(const SimulationSpec& spec);
// What a simulation's set-up builds: the ray scene and bounce grid only for pulses, and the
// contact graph only for pulses into a scene that conducts (without pulses no step runs).
bool builds_ray_scene(const SimulationSpec& spec);
bool builds_contact_graph(const SimulationSpec& spec);

// Energy ledger of a run, J (MODEL.md section 6).
struct EnergyLedger {
  double injected = 0, absorbed = 0, escaped = 0, cutoff = 0;  // optics
  double in_flight = 0;  // carried by rays still live (a run stopped mid-pulse)
  double stored = 0, vaporized = 0, walls = 0;  // heat
  double optics_imbalance() const { return injected - absorbed - escaped - cutoff - in_flight; }
  double heat_imbalance() const { return absorbed - stored - vaporized - walls; }
  // The heat ledger's scale: the larger of the heat that came in (absorbed, from walls that heat,
  // and given up by a bed that cooled) and the heat that went (stored by one that warmed,
  // vaporised, to walls that cool), each counted once (a faint beam's 1e-43 J against 3.7e-7 J
  // from the walls read as open by 1e34; a bed's heat given to the walls counted twice, as
  // stored and as to the walls); and the imbalance relative to it (NaN stays NaN).
  double heat_scale() const {
    return std::max(absorbed + std::max(-walls, 0.0) + std::max(-stored, 0.0),
                    std::max(stored, 0.0) + vaporized + std::max(walls, 0.0));
  }
  double heat_error() const { return std::abs(relative_heat_imbalance()); }
  // Signed, as the run's table prints them; over no energy at all, the imbalance itself (a floor
  // of 1e-300 made 5e-309 J open of 5.6e-309 J read as 5e-9).
  double relative_heat_imbalance() const {
    const double scale = heat_scale();
    return scale > 0 ? heat_imbalance() / scale : heat_imbalance();
  }
  double relative_optics_imbalance() const {
    return injected > 0 ? optics_imbalance() / injected : optics_imbalance();
  }
  // How far a ledger may be open, relative: the optics one to round-off (it closes by
  // construction), the heat one to the solver's tolerance, max(1e-6, 1e4 thermal.tolerance).
  static constexpr double kOpticsTolerance = 1e-9;
  static double heat_tolerance(double solver_tolerance) {
    return std::max(1e-6, 1e4 * solver_tolerance);
  }
};

struct StageTime {
  double seconds = 0;
  std::uint64_t calls = 0;
  std::string skipped_because;  // why the stage never ran, when calls == 0
};

// The figures a run reports (INTERFACE.md summary.json, history.csv).
struct Figures {
  double time = 0;                        // s, simulated
  int pulse = 0;                          // pulses launched so far
  double vaporized_fraction = 0;          // v_v, volume of vaporised / volume of all particles
  double melted_fraction = 0;             // volume liquid now / volume of all particles
  std::optional<double> max_temperature;  // K, peak of live particles over the run so far; none
                                          // without particles or with all passed in dead
  std::size_t particles = 0;              // particles in the scene, vaporised ones included
  EnergyLedger energy;
};

struct Counts {
  // segments: those traced; primaries_reused: first hits taken from an earlier pulse instead.
  std::uint64_t particles = 0, rays = 0, segments = 0, steps = 0, rebuilds = 0, staggers = 0;
  std::uint64_t primaries_reused = 0;
  // With pulses.period: pulse k is due at k T_p but starts at the first step boundary after it;
  // pulses that started more than 1% of T_p late, and the longest delay (s).
  std::uint64_t late_pulses = 0;
  double max_pulse_delay = 0;
  // Particle rows over the heat steps: solved, and live. Fewer solved than live: components at
  // rest (no heat, one temperature, walls at it) kept their temperatures without a solve.
  std::uint64_t heat_rows_solved = 0, heat_rows_live = 0;
  // Chunks of rays (64 each with a fixed thermal.dt, else 256) with a live ray, over the traces:
  // run, and live. Fewer run than live: chunks whose rays were all in free flight through a step,
  // left alone.
  std::uint64_t ray_chunks_run = 0, ray_chunks_live = 0;
  // Heat steps whose latent-heat corrector stopped at its pass cap with a band still newly crossed.
  std::uint64_t capped_phase_steps = 0;
  // Particle steps charged a latent band for a crossing their corrected step fell short of, and
  // the latent heat so charged (J; StepReport::bands_short).
  std::uint64_t bands_short = 0;
  double band_heat_short = 0;
  // Steps whose stagger found no phases consistent with the rays: ones that stopped at
  // thermal.max_staggers with the optics still changing, and ones whose redos alternated between
  // two sets of phases (a 2-cycle, stopped at its second pass).
  std::uint64_t capped_stagger_steps = 0, stagger_cycles = 0;
  // Particles whose phase alternated in those 2-cycles, summed over the steps: the phase
  // decisions each such step left to the cycle's second pass.
  std::uint64_t stagger_cycle_particles = 0;
  // Heat steps solved by an iteration (fixed-point or CG, chosen or picked by "auto"): only their
  // temperatures carry thermal.tolerance's error; the factorisation's carry round-off.
  std::uint64_t iterative_heat_steps = 0;
};

// Steps of thermal.dt per light crossing of the sample (sample.size / c / dt); 0 for one step
// per pulse flight.
double steps_per_crossing(const SimulationSpec& spec);
// The least fixed thermal.dt (kMaxStepsPerCrossing), as a refusal states it: "must be >=
// sample.size / c / 1e9 = ... s (light crosses the sample in ... s)".
std::string least_step_limit(const SimulationSpec& spec);

// What the spec alone says of the run it asks for, one line each, before any set-up: a fixed dt
// of millions of steps per light crossing or per pulse period, walls of pi K R with K = 0 that
// take no heat. Legal, and seldom meant; the CLI prints them as warnings before it sets up.
std::vector<std::string> spec_warnings(const SimulationSpec& spec);
// Parts of Simulation::run_warnings(), of a spec and its figures: the ledgers close within
// EnergyLedger::kOpticsTolerance of the injected energy and EnergyLedger::heat_tolerance of the
// heat moved, one line per open one; and temperatures risen so far that the heat solves' relative
// accuracy, in kelvin, nears the gap between melting and vaporising, one line saying so.
std::vector<std::string> open_ledger_warnings(const SimulationSpec& spec, const EnergyLedger& e);
std::optional<std::string> phase_resolution_warning(const SimulationSpec& spec, const Figures& f,
                                                    const Counts& counts);
// A temperature below a run's floor (Simulation::temperature_floor) by more than round-off (1e-12
// of it; the factorisation's worst is 1e-15): heating, conduction, walls and latent bands cannot
// take a particle there (the maximum principle of (3.10) at phi = 1, and of the steps phi < 1
// takes within its monotone limit).
inline bool below_floor(double temperature, double floor) {
  return temperature < floor * (1 - 1e-12);
}
// Particles that ended below `floor`, one line naming the coldest: an iterative solve's error
// where one ran, else a defect.
std::optional<std::string> below_floor_warning(const SimulationSpec& spec, double floor,
                                               const Particles& p, const Counts& counts);

struct SavedRun;  // a checkpoint read whole (simulation.cpp)

// The format of Simulation::write_state, the first value it writes; read_state reads no other.
// 4: Counts has the pulse delays; 5: the heat rows; 6: the path clock, ray chunks; 7: reused first
// hits; 8: the ray paths recorded since the last pulse ended (output.rays); 9: the stagger's
// counts; 10: the bands charged short; 11: the iterative heat steps; 12: the stagger cycles'
// particles; 13: the heat solve's reference temperature.
inline constexpr std::uint32_t kStateFormat = 13;

class Simulation {
 public:
  // The stages the simulation times: those of its steps, and the contact graph's first build, at
  // set-up, as `rebuild`. Its caller's reading and writing are not among them (it cannot see
  // them): the command line times its own `setup` and `output` around these (README), and any
  // caller may time its own the same way.
  static constexpr const char* kStageNames[] = {"trace", "heat", "phases", "stagger", "rebuild"};
  static constexpr int kStages = 5;

  explicit Simulation(SimulationSpec spec);  // packing from spec.packing
  // Packing given, and checked as a packing's particles are. Of spec.packing: sample_size sizes
  // the cube [0, D]^3 and the beam (diameter_fraction D); initial_temperature is where
  // saved_packing starts particles and what spec_warnings and run_warnings measure rises from
  // (each particle starts at its own temperature); seed is named in failure messages; source =
  // "file" marks particles read from packing.file (messages then name file_radius).
  Simulation(SimulationSpec spec, Particles particles);
  // Neither copied nor moved: the tracer and the heat model hold references to its particles.
  // Keep several through std::unique_ptr.
  Simulation(const Simulation&) = delete;
  Simulation& operator=(const Simulation&) = delete;
  ~Simulation();

  // One time step of MODEL.md section 5. Returns whether steps remain: the step that ends the run
  // returns false, so `do { ... } while (sim.step())` sees every step, `while (sim.step())` not
  // the last. A step that throws leaves the simulation half-stepped (its rays traced, its heat
  // not): every later step() throws RunError; restore a state saved before it into a new
  // Simulation. A throw from on_pulse_end is the exception: see there.
  bool step();
  // Steps until done or until `stop` becomes true.
  void run(const std::atomic<bool>* stop = nullptr);
  // Called with k when pulse k's time is over: just before pulse k+1 launches, or after the last
  // step. With pulses.period shorter than a pulse's flight, pulse k's rays are still in flight
  // then (the figures count them in the ledger's in_flight bin). It runs inside a step: step()
  // or run() called from it throws InputError (it recursed until the stack ran out). What it
  // throws reaches the caller of step() or run(), and the simulation stays whole: it is called
  // at a pulse boundary (before the step's trace, or after the run's last step), so the next
  // step() calls it again for the same pulse and goes on (the call after the last step is not
  // repeated).
  void on_pulse_end(std::function<void(int pulse)> callback) {
    on_pulse_end_ = std::move(callback);
  }
  bool done() const;
  // A step threw and left the simulation half-stepped (not a throw from on_pulse_end).
  bool failed() const { return failed_; }

  const Particles& particles() const { return particles_; }
  // The least of the particles' temperatures as built and the walls': none can end below it.
  double temperature_floor() const { return temperature_floor_; }
  const std::vector<double>& absorbed() const { return absorbed_; }  // J per particle, cumulative
  Figures figures() const;                                           // one pass over the particles
  int pulses_launched() const { return launched_; }  // Figures::pulse, without that pass
  Counts counts() const;
  // Time and calls per stage; a stage that never ran says why (the run reports what it skipped).
  std::array<StageTime, kStages> stages() const;
  const SimulationSpec& spec() const { return spec_; }
  // What the scene as set up will not do though its spec names it, one line each: a beam whose
  // tube meets no particle, a wall that touches none, time that cannot advance. Legal, and almost
  // always a mistake (a file packing outside the cube the beam is centred on); the CLI prints them
  // as warnings.
  std::vector<std::string> scene_warnings() const;
  // What the run so far says of its own results, one line each, from its counts, figures and
  // spec: pulses that started late (a step longer than the period), heat steps whose latent-heat
  // correction stopped at its cap, steps whose stagger did not settle (at the cap, or in a cycle),
  // an open energy ledger, temperatures beyond what the heat solves resolve between melting and
  // vaporising. Empty when all is well; the CLI prints them as warnings at a run's end. Call it
  // after run() (or between steps: it judges the steps taken so far).
  std::vector<std::string> run_warnings() const;
  // The rays every pulse launches (pulse 0's until a launch resamples); without pulses, none.
  const Beam& beam() const { return beam_; }
  const Tracer& tracer() const { return *tracer_; }
  // Ray paths: while on, the segments of accepted steps are kept until taken.
  void record_ray_paths(bool on) { tracer_->record_segments(on); }
  std::vector<RaySegment> take_ray_paths() { return std::exchange(ray_paths_, {}); }

  // Checkpoint: the complete state between two steps (particles, rays, heat, clocks, counters).
  // Restoring it into a Simulation built from the same spec continues bit-identically. The state
  // holds no spec: read_state checks the packing, not the rest (a state of K = 50 read into a
  // spec of K = 10 goes on with K = 10); keeping them together is the caller's (the command line
  // stores the run file with its checkpoint and refuses --set on a resume).
  void write_state(StateWriter& out) const;
  void read_state(StateReader& in);
  // The particles a state was written for (centres, radii, materials), as a new simulation of
  // `spec` starts them (at its initial temperature, solid, alive), read from a copy of its
  // reader: a resumed run needs no packing file. Simulation(spec, saved_packing(r, spec))
  // followed by read_state(r). InputError for a sphere or material the spec cannot hold.
  static Particles saved_packing(StateReader in, const SimulationSpec& spec);

 private:
  void restore_saved_run(SavedRun& s);  // read_state's writes, every check behind it
  // The particles are spec_.packing's generated ones (random-overlap, rsa, lattice), made here
  // with its checks; a file's, or a caller's, are checked and judged as given.
  bool generated_packing() const { return packing_from_spec_ && spec_.packing.source != "file"; }
  // What one pass of trace, heat and phases leaves (the last pass, with a stagger's redos).
  struct StepOutcome {
    StepReport report;
    double dt = 0;
    std::size_t chunks_run = 0, chunks_live = 0;
  };
  bool take_step();
  StepOutcome trace_and_heat(double budget);
  void refuse_heat_without_time(double dt) const;
  StepReport heat_and_phases(double dt);
  void book_step(const StepOutcome& step);
  void check_finite_and_note_peak();
  void mark_dead_as_vapour();
  double set_up_beam();
  void set_up_tracer();
  void set_up_thermal();
  bool pulse_due() const;
  void launch_due_pulses();
  void launch_pulse();
  void use_beam(Beam beam);
  double step_length(bool traced) const;
  void remove_vaporized(const std::vector<std::uint32_t>& ids);
  [[noreturn]] void non_finite(std::size_t particle, double temperature, double deposit) const;
  static Phase optical(Phase phase);
  void note_pulse_delay(double delay);
  void end_pulse(int pulse);
  Beam resampled_beam(int pulse) const;
  void name_step_for_checks() const;
  void check_ledgers_close() const;
  // (particle, phase) pairs sorted by particle: phases the rays see instead of the particles'.
  using PhaseOverride = std::vector<std::pair<std::uint32_t, Phase>>;
  bool optics_changed(const PhaseOverride& seen) const;
  PhaseOverride optics_after_step() const;
  static std::size_t particles_differing(const PhaseOverride& a, const PhaseOverride& b);
  void swap_phases(PhaseOverride& seen);
  void volume_fractions(Figures& f) const;
  std::string skip_reason(int stage) const;
  Simulation(SimulationSpec spec, Particles particles, bool packing_from_spec);
  void check_run_numbers() const;
  void check_thermal_masses(double run_energy) const;
  std::string radius_origin(std::size_t particle) const;
  void check_step_limit() const;
  void check_substeps(double step, const std::string& made_by) const;
  StepReport heat_step(double dt);

  SimulationSpec spec_;
  Particles particles_;
  Beam beam_;
  std::vector<double> ray_energy_;  // E_k of beam_'s rays in a pulse (computed with the beam)
  std::unique_ptr<Tracer> tracer_;
  std::unique_ptr<ThermalModel> thermal_;
  bool packing_from_spec_;  // the particles are spec_.packing's (radius_origin names its keys)
  std::vector<double> absorbed_;       // cumulative J per particle
  std::vector<double> deposits_;       // this step's dH
  std::vector<std::uint32_t> heated_;  // the particles with a deposit this step (zero elsewhere)
  std::vector<RaySegment> ray_paths_;
  double time_ = 0, next_pulse_time_ = 0, max_temperature_ = 0;
  double temperature_floor_ = 0;
  CompensatedSum total_volume_;  // of all particles, vaporised ones included
  int launched_ = 0;
  bool failed_ = false;      // a step threw: the simulation is half-stepped and refuses more
  std::string failed_step_;  // what that step threw
  std::array<StageTime, kStages> stages_{};
  Counts counts_{};
  std::function<void(int)> on_pulse_end_;
  bool in_callback_ = false;     // on_pulse_end_ is running: a step() now would re-enter this one
  bool callback_threw_ = false;  // on_pulse_end_ threw: the step stopped at a pulse boundary
};

}  // namespace beampack
