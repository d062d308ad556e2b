#include "tools/run_command.h"

#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <string_view>
#include <thread>

#include <fcntl.h>
#include <signal.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include "engine/build_info.h"
#include "geometry/error.h"
#include "geometry/input_file.h"
#include "tools/params.h"
#include "tools/part_builds.h"
#include "tools/quit_cleanup.h"
#include "tools/svg_plot.h"
#include "tools/writers.h"

namespace beampack::tools {
namespace fs = std::filesystem;

std::atomic<bool>& stop_requested() {
  static std::atomic<bool> flag{false};
  return flag;
}

namespace {

// Nanoseconds on the monotonic clock (clock_gettime is async-signal-safe).
std::int64_t monotonic_ns() {
  timespec t{};
  ::clock_gettime(CLOCK_MONOTONIC, &t);
  return std::int64_t(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

// When the first interrupt arrived (0: none yet), and its signal.
std::atomic<std::int64_t> first_interrupt_ns{0};
std::atomic<int> first_interrupt_signal{0};

// Set while a simulation is set up on a worker thread (set_up_unless_interrupted): the first
// interrupt then ends the command at once, and the main thread says so.
std::atomic<bool> setting_up{false};

// Set while a progress line is rewritten in place on a terminal, with no newline after it yet: an
// interrupt's note starts a line of its own then, and only then (under --quiet it began with an
// empty line).
std::atomic<bool> progress_line_open{false};

// Set while a command reads its input before its first set-up (a packing file for xi R / c, say):
// that read is not cut short, and no step is there to stop after.
std::atomic<bool> reading_input{false};

// Set while a finished run writes its files: an interrupt then has no step to stop after, and the
// files are written whole (exit 0); a second one quits without them.
std::atomic<bool> writing_results{false};

// An interrupted set-up left running on its thread: the process ends without running its static
// destructors (TBB's and Embree's state), which that thread may still be using.
std::atomic<bool> set_up_left_running{false};

// The first SIGINT or SIGTERM asks the run to stop between steps and write what it has (or ends a
// set-up at once: set_up_unless_interrupted); a second one ends the process at once, for a step
// that would keep the user waiting. One sent to the process and to its process group arrives
// twice, microseconds apart (`timeout -s INT`, a batch system's SIGTERM): a second within 0.2 s is
// that same interrupt, not a second one (it ended a sanitizer build's run at once, status 130,
// without its results).
void on_interrupt(int signal) {
  constexpr std::int64_t kSameInterruptNs = 200'000'000;
  const std::int64_t now = monotonic_ns();
  // One compare-and-swap: two deliveries handled on two threads at once see one first interrupt.
  std::int64_t first = 0;
  if (!first_interrupt_ns.compare_exchange_strong(first, now)) {
    if (now - first < kSameInterruptNs) return;
    remove_on_quit();  // no destructor runs: the temporaries and the empty --out folders go here
    std::signal(signal, SIG_DFL);
    ::kill(::getpid(), signal);
    return;
  }
  first_interrupt_signal.store(signal);
  stop_requested().store(true);
  if (setting_up.load()) return;  // the set-up ends at once; the main thread says so
  static constexpr char kNote[] =
      "\nbeampack: stopping after the current step; interrupt again to quit at once\n";
  static constexpr char kReading[] =
      "\nbeampack: interrupted while the input is read: the run ends when the read does, before "
      "its "
      "set-up; interrupt again to quit at once\n";
  static constexpr char kWriting[] =
      "\nbeampack: the run has ended and is writing its files: they are finished first; "
      "interrupt again to quit at once, without them\n";
  const std::size_t skip = progress_line_open.load() ? 0 : 1;  // the newline that ends it
  const auto say = [skip](const char* text, std::size_t size) {
    [[maybe_unused]] const auto written = ::write(STDERR_FILENO, text + skip, size - 1 - skip);
  };
  if (reading_input.load()) say(kReading, sizeof kReading);
  else if (writing_results.load()) say(kWriting, sizeof kWriting);
  else say(kNote, sizeof kNote);
}

// A set-up of seconds (the packing, its contacts, the ray scene: ~11 s at 3e6 particles) passes
// without a word before the first progress line: say what is being set up; and the writes of a
// run's end, by its particles alone.
bool takes_seconds(std::size_t particles, std::size_t rays) {
  return particles >= 200'000 || rays >= 1'000'000;
}

// What the set-up builds.
std::string set_up_parts(const SimulationSpec& sim) {
  std::string parts = "packing";
  if (builds_contact_graph(sim)) parts += ", contacts";
  if (builds_ray_scene(sim)) parts += ", ray scene";
  return parts;
}

void announce_set_up(std::size_t particles, std::size_t rays, const std::string& parts,
                     const std::string& label) {
  std::fprintf(stderr, "beampack: %ssetting up %zu particles and %zu rays a pulse (%s)\n",
               label.c_str(), particles, rays, parts.c_str());
}

// SIGQUIT (Ctrl-\\) asks to quit at once, with a core dump where the system keeps them: the
// temporary file being written and the empty --out folders go first, as for a second interrupt.
void on_quit(int signal) {
  remove_on_quit();
  std::signal(signal, SIG_DFL);
  ::kill(::getpid(), signal);
}

// `handler` for `signal`, unless the process started with it ignored (SIG_IGN is inherited).
void catch_unless_ignored(int signal, void (*handler)(int)) {
  struct sigaction now {};
  if (::sigaction(signal, nullptr, &now) == 0 && now.sa_handler == SIG_IGN) return;
  std::signal(signal, handler);
}

}  // namespace

// Descriptors 0-2 closed by the caller (`2>&-`) would be taken by the next files opened: the
// interrupt note, written to descriptor 2, then landed in a row of particles.csv. They are held
// open on /dev/null instead.
bool keep_standard_streams_open() {
  bool stdout_closed = false;
  for (int fd = 0; fd <= 2; ++fd)
    if (::fcntl(fd, F_GETFD) == -1 && errno == EBADF) {
      stdout_closed |= fd == STDOUT_FILENO;
      const int null = ::open("/dev/null", fd == 0 ? O_RDONLY : O_WRONLY);
      if (null >= 0 && null != fd) ::close(null);  // lowest free descriptor: null == fd
    }
  return stdout_closed;
}

void install_interrupt_handler() {
  stop_requested();  // the flag exists before a signal can arrive
  std::signal(SIGINT, on_interrupt);
  std::signal(SIGTERM, on_interrupt);
  // The terminal closed or the ssh session lost; SIGQUIT (Ctrl-\\). Both unless the caller
  // ignores them: `nohup` ignores SIGHUP, and a script's background jobs SIGQUIT.
  catch_unless_ignored(SIGHUP, on_interrupt);
  catch_unless_ignored(SIGQUIT, on_quit);
  // Output piped into a reader that quits early (`| head`): the lines are lost, not the run's
  // files, which sweep and converge write after their per-run lines.
  std::signal(SIGPIPE, SIG_IGN);
  // A file-size limit (`ulimit -f`): a write past it fails as a full disk does (a failed run that
  // leaves no half file), instead of the signal killing the process amid its temporaries.
  std::signal(SIGXFSZ, SIG_IGN);
}

std::unique_ptr<Simulation> set_up_unless_interrupted(const RunConfig& config, bool quiet,
                                                      const std::string& label,
                                                      std::optional<StateReader> state) {
  struct SetUp {
    std::mutex mutex;
    std::condition_variable finished;
    bool done = false;
    std::unique_ptr<Simulation> sim;
    std::exception_ptr error;
    std::atomic<bool> announced{false};
  };
  if (stop_requested().load()) return nullptr;
  const auto began = std::chrono::steady_clock::now();
  const auto shared = std::make_shared<SetUp>();
  setting_up.store(true);
  reading_input.store(false);
  // The worker owns a copy of the configuration and its share of the result: when an interrupt
  // leaves it running, the caller's frame is gone before it ends.
  const std::string parts = set_up_parts(config.sim) + (state ? ", checkpoint's state" : "");
  const auto counted =
      [quiet, label, rays = config.sim.beam.rays, parts, shared](std::size_t particles) {
    if (!quiet && !stop_requested().load() && takes_seconds(particles, rays)) {
      announce_set_up(particles, rays, parts, label);
      shared->announced.store(true);
    }
  };
  std::thread worker([shared, config, counted, state = std::move(state)]() mutable {
    std::unique_ptr<Simulation> sim;
    std::exception_ptr error;
    try {
      sim = start_simulation(config, counted);
      if (state) sim->read_state(*state);
    } catch (...) {
      error = std::current_exception();
    }
    const std::lock_guard lock(shared->mutex);
    shared->sim = std::move(sim), shared->error = error, shared->done = true;
    shared->finished.notify_one();
  });
  std::unique_lock lock(shared->mutex);
  constexpr auto kPoll = std::chrono::milliseconds(25);
  while (!shared->finished.wait_for(lock, kPoll, [&] { return shared->done; })) {
    if (!stop_requested().load()) continue;
    set_up_left_running.store(true);
    setting_up.store(false);
    worker.detach();
    return nullptr;
  }
  lock.unlock();
  worker.join();
  setting_up.store(false);
  if (shared->error) std::rethrow_exception(shared->error);
  // An interrupt between the set-up's end and here printed no note: it still ends the run here.
  if (stop_requested().load()) return nullptr;
  if (shared->announced.load())  // the seconds before the first progress line, accounted for
    std::fprintf(stderr, "beampack: %sset up in %.1f s\n", label.c_str(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - began).count());
  return std::move(shared->sim);
}

void note_reading_input() {
  reading_input.store(true);
}

int interrupted_exit_code() {
  const int signal = first_interrupt_signal.load();
  return 128 + (signal > 0 ? signal : SIGINT);
}

int exit_code(int code) {
  if (!set_up_left_running.load()) return code;
  std::fflush(nullptr);
  std::_Exit(code);
}

void PulsePace::observe(int launched, double elapsed) {
  if (first_ < 0) {  // the pulse under way when first seen: its launch time is unknown
    first_ = latest_ = launched;
    first_at_ = latest_at_ = -1;
    return;
  }
  if (launched == latest_) return;
  if (first_at_ < 0) first_ = launched, first_at_ = elapsed;  // the first launch seen
  latest_ = launched, latest_at_ = elapsed;
}

double PulsePace::seconds_left(int count, double elapsed) const {
  if (first_at_ < 0 || latest_ == first_) return std::numeric_limits<double>::quiet_NaN();
  const double pace = (latest_at_ - first_at_) / (latest_ - first_);
  return std::max(0.0, pace * (count - latest_ + 1) - (elapsed - latest_at_));
}

namespace {

using Clock = std::chrono::steady_clock;

// The "s" of a count's noun: "1 call", "2 calls".
const char* plural(long long count) {
  return count == 1 ? "" : "s";
}

double seconds_since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// "; x% of <what>, <rest>" when a stage left part of its work out, else nothing.
std::string share_note(std::uint64_t done, std::uint64_t all, const char* what) {
  if (done >= all) return "";
  char text[96];
  std::snprintf(text, sizeof text, "; %.3g%% of %s", 100.0 * double(done) / double(all), what);
  return text;
}

// What the heat stage (components at rest) and the trace stage (chunks of rays in free flight
// throughout a step) left out, if anything.
std::string stage_note(std::string_view stage, const Counts& c) {
  if (stage == "heat")
    return share_note(c.heat_rows_solved, c.heat_rows_live,
                      "particle rows solved, the rest at rest");
  if (stage == "trace")
    return share_note(c.ray_chunks_run, c.ray_chunks_live,
                      "ray chunks traced, the rest in free flight");
  return "";
}

// The peak temperature as printed: a particle-free scene has none (not 0 K).
std::string peak_text(const Figures& f, const char* format) {
  return shown(f.max_temperature, format, "- (no particles)");
}

// "~12 s left", "~3.5 min left", "~2.0 h left"; empty without an estimate.
std::string time_left_text(double seconds) {
  if (!(seconds >= 0)) return "";
  char text[32];
  if (seconds < 120) std::snprintf(text, sizeof text, "~%.0f s left", seconds);
  else if (seconds < 7200) std::snprintf(text, sizeof text, "~%.1f min left", seconds / 60);
  else std::snprintf(text, sizeof text, "~%.1f h left", seconds / 3600);
  return text;
}

// Progress on stderr (progress_due, progress_text).
class Progress {
 public:
  Progress(bool quiet, std::string label)
      : quiet_(quiet), terminal_(::isatty(STDERR_FILENO) == 1), label_(std::move(label)) {}
  void update(const Simulation& sim) {
    if (quiet_) return;
    const double elapsed = seconds_since(start_);
    pace_.observe(sim.pulses_launched(), elapsed);  // at every step: the pace is known sooner
    if (!progress_due(elapsed, last_shown_, terminal_)) return;
    last_shown_ = elapsed;
    const Figures f = sim.figures();
    const int count = sim.spec().pulses.count;
    const std::string left = time_left_text(pace_.seconds_left(count, elapsed));
    char line[256];
    std::snprintf(line, sizeof line, "pulse %d/%d  t = %.3e s  v_v = %.4f  T_max = %s  %.1f s%s%s",
                  f.pulse, count, f.time, f.vaporized_fraction, peak_text(f, "%.0f K").c_str(),
                  elapsed, left.empty() ? "" : "  ", left.c_str());
    std::fputs(progress_text(label_ + line, terminal_).c_str(), stderr);
    progress_line_open.store(terminal_);
  }
  ~Progress() {
    if (last_shown_ && terminal_) std::fprintf(stderr, "\n");
    progress_line_open.store(false);
  }

 private:
  bool quiet_;
  bool terminal_;  // stderr is a terminal: the line is rewritten in place
  std::string label_;
  Clock::time_point start_ = Clock::now();
  std::optional<double> last_shown_;
  PulsePace pace_;
};

}  // namespace

bool progress_due(double elapsed, std::optional<double> last_shown, bool terminal) {
  if (elapsed < 2.0) return false;
  return !last_shown || elapsed - *last_shown >= (terminal ? 0.5 : 30.0);
}

std::string progress_text(const std::string& line, bool terminal) {
  return terminal ? "\r" + line + "   " : line + "\n";
}

namespace {

// The figures of a run as CSV columns: history.csv and sweep.csv share them.
const char* kFigureColumns =
    "vaporized_fraction,melted_fraction,max_temperature_K,injected_J,absorbed_J,escaped_J,"
    "cutoff_J,stored_J,vaporized_J,walls_J,in_flight_J";

std::string figure_columns(const Figures& f) {
  const EnergyLedger& e = f.energy;
  std::ostringstream s;
  s << exact(f.vaporized_fraction) << ',' << exact(f.melted_fraction) << ','
    << exact(f.max_temperature) << ',' << exact(e.injected) << ',' << exact(e.absorbed) << ','
    << exact(e.escaped) << ',' << exact(e.cutoff) << ',' << exact(e.stored) << ','
    << exact(e.vaporized) << ',' << exact(e.walls) << ',' << exact(e.in_flight);
  return s.str();
}

std::string history_header() {
  return std::string("time_s,pulse,") + kFigureColumns + "\n";
}

std::string history_row(const Figures& f) {
  return exact(f.time) + ',' + std::to_string(f.pulse) + ',' + figure_columns(f) + '\n';
}

nlohmann::json toml_to_json(const toml::table& table) {
  nlohmann::json j = nlohmann::json::object();
  for (const auto& [k, node] : table) {
    const std::string key(k.str());
    if (const auto* t = node.as_table()) j[key] = toml_to_json(*t);
    else if (const auto* v = node.as_floating_point()) j[key] = v->get();
    else if (const auto* i = node.as_integer()) j[key] = i->get();
    else if (const auto* b = node.as_boolean()) j[key] = b->get();
    else if (const auto* s = node.as_string()) j[key] = s->get();
  }
  return j;
}

// The stages `beampack run` times itself, around the simulation's (Simulation::kStageNames, what
// its steps run), which cannot see them: `setup`, from the run's start to its simulation ready to
// step (the packing made or read, the ray scene, a checkpoint restored; the contact graph's first
// build is the simulation's `rebuild`), and `output`, the run's files (a pulse end's history row,
// frame and ray paths, a checkpoint, the files of the run's end, those a resume carries over).
// Summed over the parts of a resumed run, as the simulation's are.
struct CommandStages {
  StageTime setup, output;
};

// Adds a part's set-up to `setup`: `elapsed` since the run's start (less the writes in it), but the
// simulation's own stage time in it, the contact graph's first build, which its `rebuild` stage
// counts. A restored state replaces the simulation's stage times with the earlier parts', and
// that build's time is then the set-up's.
void count_set_up(StageTime& setup, const Simulation& sim, bool restored, double elapsed) {
  double simulation_stages = 0;
  if (!restored)
    for (const StageTime& s : sim.stages()) simulation_stages += s.seconds;
  setup.seconds += elapsed - simulation_stages;
  ++setup.calls;
}

// The set-up, then the simulation's stages, in the order they run.
StageTable set_up_and_simulation_stages(const Simulation& sim, const StageTime& setup) {
  StageTable out{{"setup", setup}};
  const auto times = sim.stages();
  for (int k = 0; k < Simulation::kStages; ++k)
    out.emplace_back(Simulation::kStageNames[k], times[k]);
  return out;
}

// Every stage of a run, in the order it runs: the set-up, the simulation's, the output. The
// command's own never skip (a run that writes its figures was set up and writes them).
StageTable run_stages(const Simulation& sim, const CommandStages& own) {
  StageTable out = set_up_and_simulation_stages(sim, own.setup);
  out.emplace_back("output", own.output);
  return out;
}

// A line of a stage table: the stage's seconds, its calls and `note`; or, never run, why not.
std::string stage_line(const std::string& name, const StageTime& s, const std::string& note) {
  char text[128];
  if (s.calls == 0) {
    std::snprintf(text, sizeof text, "  %-26s %14s  skipped: ", name.c_str(), "-");
    return text + s.skipped_because;
  }
  std::snprintf(text, sizeof text, "  %-26s %14.4f  (%llu call%s)", name.c_str(), s.seconds,
                static_cast<unsigned long long>(s.calls), plural(s.calls));
  return text + note;
}

// `earlier_parts`: the builds that ran the parts of a resumed run before this one.
nlohmann::json summary_json(const Simulation& sim, const RunResult& r, const RunConfig& config,
                            const std::vector<PartBuild>& earlier_parts, const CommandStages& own) {
  const Figures& f = r.figures;
  const EnergyLedger& e = f.energy;
  nlohmann::json j;
  j["vaporized_fraction"] = f.vaporized_fraction;
  j["melted_fraction"] = f.melted_fraction;
  j["max_temperature_K"] =
      f.max_temperature ? nlohmann::json(*f.max_temperature) : nlohmann::json(nullptr);
  j["time_s"] = f.time;
  j["pulses"] = f.pulse;
  j["pulses_ended"] = r.pulses_ended;
  j["energy_J"] = {{"injected", e.injected},   {"absorbed", e.absorbed}, {"escaped", e.escaped},
                   {"in_flight", e.in_flight}, {"cutoff", e.cutoff},     {"stored", e.stored},
                   {"vaporized", e.vaporized}, {"walls", e.walls}};
  j["counts"] = {{"particles", r.counts.particles},
                 {"rays", r.counts.rays},
                 {"segments", r.counts.segments},
                 {"primaries_reused", r.counts.primaries_reused},
                 {"steps", r.counts.steps},
                 {"rebuilds", r.counts.rebuilds},
                 {"staggers", r.counts.staggers},
                 {"late_pulses", r.counts.late_pulses},
                 {"heat_rows_solved", r.counts.heat_rows_solved},
                 {"heat_rows_live", r.counts.heat_rows_live},
                 {"ray_chunks_run", r.counts.ray_chunks_run},
                 {"ray_chunks_live", r.counts.ray_chunks_live},
                 {"capped_phase_steps", r.counts.capped_phase_steps},
                 {"bands_short", r.counts.bands_short},
                 {"band_heat_short_J", r.counts.band_heat_short},
                 {"capped_stagger_steps", r.counts.capped_stagger_steps},
                 {"iterative_heat_steps", r.counts.iterative_heat_steps},
                 {"stagger_cycle_particles", r.counts.stagger_cycle_particles},
                 {"stagger_cycles", r.counts.stagger_cycles}};
  j["max_pulse_delay_s"] = r.counts.max_pulse_delay;
  nlohmann::json stages = nlohmann::json::object();
  for (const auto& [name, s] : run_stages(sim, own))
    stages[name] = {{"seconds", s.seconds},
                    {"calls", s.calls},
                    {"skipped", s.calls == 0},
                    {"skipped_because", s.skipped_because}};
  j["stages"] = stages;
  j["wall_seconds"] = r.wall_seconds;
  // What the times were taken with (--threads, or all cores; a resumed run's last part's); the
  // figures are the same on any. --threads 64 on 2 cores runs 2.
  j["threads"] = std::min<std::size_t>(
      tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism),
      static_cast<std::size_t>(tbb::this_task_arena::max_concurrency()));
  j["interrupted"] = r.interrupted;
  j["config"] = toml_to_json(config.resolved);
  j["beampack"] = part_build_json(this_build());
  j["beampack"]["version"] = build_info().version;
  if (!earlier_parts.empty()) j["beampack"]["earlier_parts"] = part_builds_json(earlier_parts);
  return j;
}

void print_table(const Simulation& sim, const RunResult& r, const CommandStages& own) {
  const Figures& f = r.figures;
  const EnergyLedger& e = f.energy;
  std::printf("%-28s %14.6g\n", "vaporized fraction", f.vaporized_fraction);
  std::printf("%-28s %14.6g\n", "melted fraction", f.melted_fraction);
  std::printf("%-28s %16s\n", "peak temperature", peak_text(f, "%14.6g K").c_str());
  std::printf("energy ledger, J\n");
  std::printf("  %-26s %14.6e\n", "injected", e.injected);
  std::printf("  %-26s %14.6e\n", "absorbed", e.absorbed);
  std::printf("  %-26s %14.6e\n", "escaped", e.escaped);
  std::printf("  %-26s %14.6e\n", "cut off", e.cutoff);
  if (e.in_flight != 0) std::printf("  %-26s %14.6e\n", "in flight (run stopped)", e.in_flight);
  std::printf("  %-26s %14.6e\n", "stored as heat", e.stored);
  std::printf("  %-26s %14.6e\n", "carried off by vapour", e.vaporized);
  std::printf("  %-26s %14.6e\n", "lost to walls", e.walls);
  if (r.counts.bands_short > 0)  // within the heat the particles took or gave
    std::printf("  %-26s %14.6e (in %llu particle (sub-)steps)\n", "latent, crossing not made",
                r.counts.band_heat_short, static_cast<unsigned long long>(r.counts.bands_short));
  std::printf("  %-26s %14.3e (optics) %10.3e (heat)\n", "imbalance, relative",
              e.relative_optics_imbalance(), e.relative_heat_imbalance());
  std::printf("stages, s\n");
  for (const auto& [name, s] : run_stages(sim, own))
    std::printf("%s\n", stage_line(name, s, stage_note(name, r.counts)).c_str());
  std::printf("%-28s %14.3f s (%llu step%s, %llu ray%s, %llu segment%s traced", "wall time",
              r.wall_seconds, static_cast<unsigned long long>(r.counts.steps),
              plural(r.counts.steps), static_cast<unsigned long long>(r.counts.rays),
              plural(r.counts.rays), static_cast<unsigned long long>(r.counts.segments),
              plural(r.counts.segments));
  if (r.counts.primaries_reused > 0)
    std::printf(", %llu primary segments (hits or misses) reused from earlier pulses",
                static_cast<unsigned long long>(r.counts.primaries_reused));
  std::printf(")\n");
}

}  // namespace

int report_failed_run(const std::string& label, const std::exception& e, const char* consequence) {
  const bool input = dynamic_cast<const InputError*>(&e) != nullptr;
  std::fprintf(stderr, "beampack: %s%s %s (%s)\n", label.c_str(),
               input ? "error:" : "run failed:", e.what(), consequence);
  return input ? 2 : 1;
}

OutDir::OutDir(const std::string& dir) {
  std::error_code ec;
  // Folder by folder as the system walks the path, not its lexical normal form: `a/../b` makes
  // `a` too, and only a record of each folder made here finds it again.
  fs::path walked;
  for (const fs::path& part : fs::absolute(dir, ec)) {
    walked /= part;
    if (part.empty() || fs::exists(walked, ec)) continue;
    const bool made = fs::create_directory(walked, ec);
    if (ec) break;
    if (made) made_.push_back(walked);
  }
  if (ec || !fs::is_directory(dir)) {
    std::error_code link_ec;  // a dangling link or a loop reads as "File exists"
    const bool dangling = fs::is_symlink(fs::symlink_status(walked, link_ec));
    const std::string why = dangling ? "a symbolic link on its path leads nowhere, or in a loop"
                            : ec     ? ec.message()
                                     : "it exists and is not a directory";
    remove_empty_made();
    throw InputError("--out " + dir + ": cannot create the output directory (" + why + ")");
  }
  lock_.emplace(dir, FolderLock::Mode::exclusive, "--out");  // before the probe: a race on its name
  if (!fs::is_directory(dir))  // removed by the command that held it (an empty folder it made)
    throw InputError("--out " + dir +
                     ": the folder was removed while this command waited for another to let go "
                     "of it; run again");
  const fs::path probe = fs::path(dir) / ".beampack-write-test";
  std::FILE* f = std::fopen(probe.c_str(), "w");
  if (!f) {
    remove_empty_made();
    throw InputError("--out " + dir + ": the output directory is not writable");
  }
  std::fclose(f);
  fs::remove(probe);
  quit_removes_folders(made_);
}

OutDir::~OutDir() {
  quit_removes_folders({});
  remove_empty_made();  // still locked: a command waiting for the folder sees it go (FolderLock)
}

namespace {

// Whether the open folder `fd` is still the one at `dir`: a holder may have removed it (an empty
// folder it made), and another command made it again, while this one waited for its lock.
bool still_there(int fd, const std::string& dir) {
  struct stat open_one {
  }, named{};
  return ::fstat(fd, &open_one) == 0 && ::stat(dir.c_str(), &named) == 0 &&
         open_one.st_dev == named.st_dev && open_one.st_ino == named.st_ino;
}

}  // namespace

// Two commands writing one folder remove each other's files (each takes the other's for an
// earlier run's, or a killed run's temporaries) and mix their results; a resume that reads a
// folder while a run writes it reads a checkpoint about to be replaced. A holder is given a
// second to let go: a run killed outright keeps the lock until the system has torn it down, and
// `timeout -s KILL` returns before that (it kills its own process group, itself too), so a
// resume straight after found the folder held.
FolderLock::FolderLock(const std::string& dir, Mode mode, const std::string& option) {
  const int operation = (mode == Mode::exclusive ? LOCK_EX : LOCK_SH) | LOCK_NB;
  for (int tries = 0; tries < 20;) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0) return;  // unreadable or gone: unlocked, and the caller's checks say why
    if (::flock(fd, operation) == 0) {
      if (still_there(fd, dir)) {
        fd_ = fd;
        return;
      }
      ::close(fd);  // a folder removed while this command waited: lock the one there now
      ++tries;
      continue;
    }
    const int why = errno;
    ::close(fd);
    if (why != EWOULDBLOCK) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    ++tries;
  }
  throw InputError(option + " " + dir +
                   ": another beampack command is writing there (it holds the folder's lock): "
                   "wait for it to end" +
                   (mode == Mode::exclusive ? ", or choose another " + option : std::string()));
}

FolderLock::~FolderLock() {
  if (fd_ >= 0) ::close(fd_);
}

// Innermost first, and only while they are empty: a folder with results in it stays, and so do
// the folders made on the way to it (`a` of `--out a/../b`), through which its path still leads.
void OutDir::remove_empty_made() {
  std::error_code ec;
  for (auto it = made_.rbegin(); it != made_.rend(); ++it)
    if (!fs::remove(*it, ec)) return;
}

std::unique_ptr<tbb::global_control> limit_threads(int threads) {
  if (threads <= 0) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                               std::size_t(threads));
}

void say_warnings(const std::string& label, const std::vector<std::string>& warnings) {
  if (!warnings.empty()) std::fflush(stdout);  // after what stdout printed, when both are piped
  for (const std::string& warning : warnings)
    std::fprintf(stderr, "beampack: %swarning: %s\n", label.c_str(), warning.c_str());
}

StageTimer::~StageTimer() {
  stage_.seconds += seconds_since(start_);
  ++stage_.calls;
}

std::set<std::string> warn_of_shared_specs(const std::vector<const RunConfig*>& configs) {
  std::vector<std::string> shared;  // in the order of the first run's, as `run` says them
  if (!configs.empty()) shared = spec_warnings(configs.front()->sim);
  for (const RunConfig* config : configs) {
    const std::vector<std::string> lines = spec_warnings(config->sim);
    std::erase_if(shared, [&](const std::string& line) {
      return std::find(lines.begin(), lines.end(), line) == lines.end();
    });
  }
  say_warnings("", shared);
  return {shared.begin(), shared.end()};
}

namespace {

// Steps the simulation to its end or an interrupt, with a progress line after `label`.
void step_until_done(Simulation& sim, bool quiet, const std::string& label) {
  Progress progress(quiet, label);
  while (!sim.done() && !stop_requested().load()) {
    sim.step();
    progress.update(sim);
  }
}

}  // namespace

RunResult run_scene(const RunConfig& config, bool quiet, const std::string& label,
                    const std::set<std::string>& said) {
  std::vector<std::string> unsaid;
  for (const std::string& line : spec_warnings(config.sim))
    if (!said.contains(line)) unsaid.push_back(line);
  say_warnings(label, unsaid);
  const auto start = Clock::now();
  const std::unique_ptr<Simulation> owned = set_up_unless_interrupted(config, quiet, label);
  if (!owned) {  // interrupted during its set-up: no figures, and not a result
    RunResult r;
    r.interrupted = true;
    return r;
  }
  Simulation& sim = *owned;
  StageTime setup;
  count_set_up(setup, sim, false, seconds_since(start));
  say_warnings(label, sim.scene_warnings());
  step_until_done(sim, quiet, label);
  RunResult r;
  r.stages = set_up_and_simulation_stages(sim, setup);
  r.figures = sim.figures();
  r.counts = sim.counts();
  r.temperature = sim.particles().temperature;
  r.alive = sim.particles().alive;
  r.interrupted = !sim.done();
  r.wall_seconds = seconds_since(start);
  if (!r.interrupted) r.run_warnings = sim.run_warnings();  // a part of a run says nothing
  return r;
}

namespace {

// The runs that skipped a stage, by why: each reason once, in the order first met, with the
// labels of its runs.
using SkipGroups = std::vector<std::pair<std::string, std::vector<std::string>>>;

// "<why> (a, b, c and 4 more)"; a reason every run of the table gave names none.
std::string skip_groups_text(const SkipGroups& groups, std::size_t runs) {
  constexpr std::size_t kNamed = 3;
  std::string text;
  for (const auto& [why, labels] : groups) {
    if (!text.empty()) text += "; ";
    text += why;
    if (labels.size() == runs) continue;
    text += " (";
    for (std::size_t k = 0; k < std::min(labels.size(), kNamed); ++k)
      text += (k > 0 ? ", " : "") + labels[k];
    if (labels.size() > kNamed) text += " and " + std::to_string(labels.size() - kNamed) + " more";
    text += ")";
  }
  return text;
}

// One stage summed over the runs (seconds and calls), with the runs that skipped it.
struct StageTotal {
  StageTime time;
  SkipGroups skipped;
  std::size_t skips = 0;
};

StageTotal total_of_stage(const std::vector<LabelledRun>& runs, std::size_t stage) {
  StageTotal total;
  for (const LabelledRun& run : runs) {
    const StageTime& s = run.stages.at(stage).second;
    total.time.seconds += s.seconds;
    total.time.calls += s.calls;
    if (s.calls > 0) continue;
    ++total.skips;
    auto group = std::find_if(total.skipped.begin(), total.skipped.end(),
                              [&](const auto& g) { return g.first == s.skipped_because; });
    if (group == total.skipped.end())
      group = total.skipped.insert(total.skipped.end(), {s.skipped_because, {}});
    group->second.push_back(run.label);
  }
  total.time.skipped_because = skip_groups_text(total.skipped, runs.size());
  return total;
}

// The shares the heat and trace stages' notes give, over every run.
Counts summed_shares(const std::vector<LabelledRun>& runs) {
  Counts sum;
  for (const LabelledRun& run : runs) {
    sum.heat_rows_solved += run.counts.heat_rows_solved;
    sum.heat_rows_live += run.counts.heat_rows_live;
    sum.ray_chunks_run += run.counts.ray_chunks_run;
    sum.ray_chunks_live += run.counts.ray_chunks_live;
  }
  return sum;
}

}  // namespace

std::string stage_columns() {
  std::string columns = "setup_s";
  for (const char* name : Simulation::kStageNames) columns += std::string(",") + name + "_s";
  return columns;
}

std::string stage_cells(const StageTable& stages) {
  std::string cells;
  for (const auto& [name, time] : stages) cells += (cells.empty() ? "" : ",") + exact(time.seconds);
  return cells;
}

std::vector<std::string> stage_total_lines(const std::vector<LabelledRun>& runs,
                                           const StageTime& output) {
  if (runs.empty()) return {};
  const std::size_t n = runs.size();
  std::vector<std::string> lines{"stages over " + std::to_string(n) + " run" +
                                 plural(static_cast<long long>(n)) + ", s"};
  const Counts shares = summed_shares(runs);
  for (std::size_t k = 0; k < runs.front().stages.size(); ++k) {
    const std::string& name = runs.front().stages[k].first;
    const StageTotal total = total_of_stage(runs, k);
    std::string note = stage_note(name, shares);
    if (total.skips > 0 && total.skips < n)
      note += "; skipped in " + std::to_string(total.skips) + " of " + std::to_string(n) +
              " runs: " + total.time.skipped_because;
    lines.push_back(stage_line(name, total.time, note));
  }
  lines.push_back(stage_line("output", output, ""));
  return lines;
}

// The first `bytes` of a regular file; "" for anything else (a FIFO would block the open).
std::string head_of(const fs::path& file, std::size_t bytes) {
  std::error_code ec;
  if (!fs::is_regular_file(file, ec)) return "";
  std::ifstream in(file, std::ios::binary);
  std::string head(bytes, '\0');
  in.read(head.data(), static_cast<std::streamsize>(bytes));
  head.resize(static_cast<std::size_t>(in.gcount()));
  return head;
}

// dir's summary.json, parsed; not an object if there is none (or it is not JSON).
nlohmann::json summary_in(const fs::path& dir) {
  return nlohmann::json::parse(head_of(dir / "summary.json", 1 << 24), nullptr, false);
}

namespace {

// Format 2 added the wall time before the checkpoint, format 3 the pulses between checkpoints,
// format 4 the optics ledger's low parts, format 5 the revisions that ran the run so far, format 6
// their build types, compilers and flags, format 7 the set-up and output stages' times so far,
// format 8 whether an interrupt wrote it; format 1 is "beampack-checkpoint". Only format 8 is
// read: every earlier one holds a simulation state of an earlier format (kStateFormat), which
// no later build reads (their readers here were reached by edited test files only).
constexpr const char* kCheckpointMagic = "beampack-checkpoint-8";

// What a run accumulates besides the simulation's own state: the history rows and the frames.
struct RunRecord {
  std::string config_text;
  std::string history = history_header();
  std::vector<std::pair<std::string, double>> frames;
  // rays.pvd's series: each pulse's ray path file and end time (not in the checkpoint: a resume
  // rebuilds it from the history rows, ray_series).
  std::vector<std::pair<std::string, double>> ray_files;
  double earlier_seconds = 0;  // wall time of the runs this one resumes
  int checkpoint_every = 0;    // --checkpoint-every of the run: a resume keeps it
  // The folder's checkpoint is the interrupt's this run resumed in place from: spent once the
  // run finishes, unless a periodic one (--checkpoint-every) has replaced it meanwhile. Read from
  // the checkpoint's flag, and cleared for a resume into another folder.
  bool spent_checkpoint_here = false;
  // The builds that ran the parts before this one, in order, one entry per resume; empty for a
  // run that did not resume.
  std::vector<PartBuild> earlier_parts;
  CommandStages stages;  // so far, the runs this one resumes included
};

// summary.json's text. A string that is not UTF-8 (a failure's message quoting a path named in
// other bytes) is written with U+FFFD in place of its bad bytes: nlohmann's default throws,
// and the run's results were lost at its end.
std::string json_text(const nlohmann::json& j) {
  return j.dump(2, ' ', false, nlohmann::json::error_handler_t::replace);
}

// `wall_seconds`: the run's wall time so far, resumed runs included; `interrupt`: written by an
// interrupt, not every --checkpoint-every pulses.
OutputFile checkpoint_file(const fs::path& path, const Simulation& sim, const RunRecord& record,
                           double wall_seconds, bool interrupt) {
  StateWriter w;
  w.text(kCheckpointMagic);
  std::vector<PartBuild> parts = record.earlier_parts;
  parts.push_back(this_build());
  write_part_builds(w, parts);
  w.value(wall_seconds);
  w.value(record.checkpoint_every);
  for (const StageTime* s : {&record.stages.setup, &record.stages.output})
    w.value(s->seconds), w.value(s->calls);
  w.value<std::uint8_t>(interrupt ? 1 : 0);
  w.text(record.config_text);
  w.text(record.history);
  w.value<std::uint64_t>(record.frames.size());
  for (const auto& [name, time] : record.frames) w.text(name), w.value(time);
  sim.write_state(w);
  auto bytes = std::make_shared<const std::string>(w.finish());
  return {path.string(),
          [bytes](std::ostream& o) { o.write(bytes->data(), std::streamsize(bytes->size())); }};
}

// Why DIR holds no checkpoint.bin: its run failed, or wrote none yet (killed before its first
// pulse ended or its first --checkpoint-every), or DIR holds no run; "" when one is there (and
// is not a regular file).
std::string no_checkpoint_why(const fs::path& path) {
  std::error_code ec;
  if (fs::exists(path, ec)) return "";
  const fs::path dir = path.parent_path();
  const nlohmann::json summary = summary_in(dir);
  if (summary.is_object() && summary.contains("failed"))
    return " (its run failed, and a failed run keeps no checkpoint but a periodic one "
           "(--checkpoint-every): run it again without --resume)";
  if (fs::is_regular_file(dir / "history.csv", ec))
    return " (its run wrote none yet: a checkpoint is written at an interrupt, and with "
           "--checkpoint-every N after every N pulses; a run killed outright before that leaves "
           "history.csv alone, and starts again without --resume)";
  return " (no checkpoint there: --resume takes the --out folder of an interrupted run)";
}

StateReader open_checkpoint(const fs::path& path, RunRecord& record) {
  if (!fs::is_regular_file(path))
    throw InputError("--resume: cannot read " + path.string() + no_checkpoint_why(path));
  // Read whole into memory: a file larger than the machine's memory is not one this machine
  // wrote (a 5 GB file of zeros took 60 s and 7.8 GB before it was found damaged).
  std::error_code size_ec;
  const std::uintmax_t file_bytes = fs::file_size(path, size_ec);
  const auto memory = static_cast<std::uintmax_t>(::sysconf(_SC_PHYS_PAGES)) *
                      static_cast<std::uintmax_t>(::sysconf(_SC_PAGE_SIZE));
  if (!size_ec && memory > 0 && file_bytes > memory)
    throw InputError("--resume: " + path.string() + " holds " + std::to_string(file_bytes) +
                     " bytes, more than this machine's memory (" + std::to_string(memory) +
                     " bytes): not a checkpoint it can resume");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError("--resume: cannot read " + path.string());
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  StateReader r(std::move(bytes), path.string());
  const std::string magic = r.text();
  const std::string again =
      ": finish that run with the build that wrote it, or run it again with this one";
  if (magic.starts_with("beampack-checkpoint") && magic != kCheckpointMagic)
    throw InputError(path.string() + ": a checkpoint of another beampack (" + magic +
                     "); this one reads " + kCheckpointMagic + " only" + again);
  if (magic != kCheckpointMagic) throw InputError(path.string() + ": not a beampack checkpoint");
  record.earlier_parts = read_part_builds(r, path.string());
  record.earlier_seconds = r.value<double>();
  record.checkpoint_every = r.value<int>();
  for (StageTime* s : {&record.stages.setup, &record.stages.output})
    s->seconds = r.value<double>(), s->calls = r.value<std::uint64_t>();
  check_checkpoint_stage_times(record.stages.setup.seconds, record.stages.output.seconds,
                               path.string());
  const auto interrupts = r.value<std::uint8_t>();
  if (interrupts > 1)
    throw InputError("--resume: damaged checkpoint " + path.string() + ": its interrupt flag is " +
                     std::to_string(interrupts) + ", not 0 or 1");
  record.spent_checkpoint_here = interrupts == 1;
  record.config_text = r.text();
  record.history = r.text();
  const auto frames = r.value<std::uint64_t>();
  for (std::uint64_t k = 0; k < frames; ++k) {
    std::string name = r.text();
    record.frames.emplace_back(std::move(name), r.value<double>());
  }
  check_checkpoint_record(record.earlier_seconds, record.checkpoint_every, record.frames,
                          path.string());
  // Refused before the set-up, which a state of another format would follow (minutes at 10^7).
  if (const std::uint32_t state = r.peek<std::uint32_t>(); state != kStateFormat)
    throw InputError(path.string() + ": written by beampack " +
                     record.earlier_parts.back().revision + " with state format " +
                     std::to_string(state) + "; this one reads state format " +
                     std::to_string(kStateFormat) + " only" + again);
  check_history_text(record.history, path.string());
  return r;
}

}  // namespace

// A pulse's file of a run: particles_0003.vtp, rays_0003.vtp (particles_10000.vtp from the
// ten-thousandth pulse on).
std::string pulse_file(const char* stem, int pulse) {
  char name[64];
  std::snprintf(name, sizeof name, "%s_%04d.vtp", stem, pulse);
  return name;
}

// The pulse number and suffix of pulse_file's names, as a pattern: four digits or more.
constexpr const char* kPulseFileNumber = R"(_\d{4,}\.vtp)";

// The frame of the state a run starts from, before its first pulse (pulse_file's frames follow).
constexpr const char* kStartFrame = "particles_start.vtp";

// A frame as pulse_file names it, or the start frame.
bool is_frame_name(const std::string& name) {
  static const std::regex frame(std::string("particles") + kPulseFileNumber);
  return name == kStartFrame || std::regex_match(name, frame);
}

void check_history_text(const std::string& history, const std::string& source) {
  for (std::size_t i = 0; i < history.size(); ++i) {
    const auto b = static_cast<unsigned char>(history[i]);
    if ((b >= 0x20 && b < 0x7F) || b == '\n') continue;
    throw InputError(source + ": its history rows hold byte " + escaped_byte(b) + " at " +
                     std::to_string(i) + " (a checkpoint edited by hand?)");
  }
}

void check_checkpoint_record(double earlier_seconds, int checkpoint_every,
                             const std::vector<std::pair<std::string, double>>& frames,
                             const std::string& source) {
  auto refuse = [&source](const std::string& what) {
    throw InputError(source + ": " + what + " (a checkpoint edited by hand?)");
  };
  if (!(std::isfinite(earlier_seconds) && earlier_seconds >= 0))
    refuse("its wall time so far, " + std::to_string(earlier_seconds) +
           " s, is not a finite number >= 0");
  if (checkpoint_every < 0)
    refuse("its --checkpoint-every, " + std::to_string(checkpoint_every) + ", is below 0");
  for (const auto& [name, time] : frames) {
    if (!is_frame_name(name))
      refuse("a frame named \"" + name + "\", not particles_NNNN.vtp or " + kStartFrame +
             " in the run's folder");
    if (!std::isfinite(time)) refuse("frame " + name + " has a time that is not finite");
  }
}

void check_checkpoint_stage_times(double setup_seconds, double output_seconds,
                                  const std::string& source) {
  for (const auto& [stage, seconds] :
       {std::pair{"set-up", setup_seconds}, {"output", output_seconds}})
    if (!(std::isfinite(seconds) && seconds >= 0))
      throw InputError(source + ": its " + stage + " time so far, " + std::to_string(seconds) +
                       " s, is not a finite number >= 0 (a checkpoint edited by hand?)");
}

// Whether dir holds a run of beampack's: its checkpoint, its frames' particles.pvd, its first
// ray paths or its history.csv (a killed run leaves only those), or its summary.json (figures and
// configuration). Files of beampack's names in a folder without any of them are the user's own.
bool holds_earlier_run(const fs::path& dir) {
  if (head_of(dir / "checkpoint.bin", 64).find("beampack-checkpoint") != std::string::npos)
    return true;
  // Any frame of ours: the start frame (a run killed before its first pulse ended leaves only it),
  // particles_0NNN.vtp, or a later first one (a resume left out deleted frames; pulse 10000 on).
  if (head_of(dir / "particles.pvd", 4096).find("file=\"particles_") != std::string::npos)
    return true;
  if (head_of(dir / "rays_0000.vtp", 256).find("<!-- written by beampack -->") != std::string::npos)
    return true;
  if (head_of(dir / "history.csv", 4096).starts_with(history_header()))  // a killed run's rows
    return true;
  const nlohmann::json j = summary_in(dir);
  return j.is_object() && j.contains("vaporized_fraction") && j.contains("config");
}

// The names of the files a run writes into its output folder, and of the temporary files it
// writes them through (a killed run can leave one).
bool is_output_name(const fs::path& file) {
  static const std::regex ours(std::string(R"(((particles|rays))") + kPulseFileNumber +
                               R"(|particles_start\.vtp|particles\.pvd|rays\.pvd|checkpoint\.bin|)"
                               R"(summary\.json|history\.csv|particles\.csv)(\.tmp\.\d+)?)");
  return std::regex_match(file.filename().string(), ours);
}

// A run file or packing file where the run writes an output would be overwritten (or removed
// as an earlier run's) before the run has read it, or after: refused. Compared as files, so a
// symlink or hard link to an output is caught too.
void refuse_outputs_over_inputs(const fs::path& dir,
                                const std::vector<std::pair<std::string, std::string>>& inputs) {
  for (const auto& [key, path] : inputs) {
    if (path.empty()) continue;
    for (const fs::directory_entry& e : fs::directory_iterator(dir)) {
      std::error_code ec;
      if (!is_output_name(e.path()) || !fs::equivalent(e.path(), path, ec)) continue;
      throw InputError(key + " = \"" + path + "\" is " + e.path().string() +
                       ", a file the run writes: choose another --out or move the file");
    }
  }
}

void refuse_non_files_at_outputs(const fs::path& dir,
                                 const std::function<bool(const fs::path&)>& is_output) {
  std::error_code listed;  // a folder that may be written but not listed (mode 300) is not checked
  for (const fs::directory_entry& e : fs::directory_iterator(dir, listed)) {
    const std::string name = e.path().filename().string();
    if (!is_output(e.path()) || name.find(".tmp.") != std::string::npos) continue;
    std::error_code ec;
    const fs::file_type type = fs::symlink_status(e.path(), ec).type();
    if (ec || type == fs::file_type::regular || type == fs::file_type::symlink) continue;
    throw InputError("--out " + dir.string() + ": " + e.path().string() + " is " +
                     (type == fs::file_type::directory ? "a folder" : "not a regular file") +
                     " where the command writes a file: move it or choose another --out");
  }
}

void refuse_non_files_at_outputs(const fs::path& dir, const std::vector<std::string>& names) {
  refuse_non_files_at_outputs(dir, [&](const fs::path& p) {
    return std::find(names.begin(), names.end(), p.filename().string()) != names.end();
  });
}

void say_nothing_written(const std::string& what, const fs::path& dir,
                         const std::vector<std::string>& names) {
  std::string found;
  for (const std::string& name : names) {
    std::error_code ec;
    if (fs::is_regular_file(dir / name, ec)) found += (found.empty() ? "" : " and ") + name;
  }
  const bool two = found.find(" and ") != std::string::npos;
  const std::string note =
      found.empty() ? ""
                    : " (" + found + " in " + dir.string() + (two ? " are" : " is") +
                          " an earlier run's, left as " + (two ? "they were)" : "it was)");
  std::fprintf(stderr, "beampack: %s: nothing written%s\n", what.c_str(), note.c_str());
}

// A new run into a directory that holds an earlier one: that run's results, checkpoint and
// frames would outlive it (a new run that fails would leave them looking like its own, and
// `--resume` would continue the earlier run over the new outputs), so they go: beampack's own
// names only, in a folder that holds a beampack run. A run resumed in its own folder keeps that
// run's files and removes only the temporaries of a write the interrupted part was killed in.
void remove_earlier_run(const fs::path& dir, bool temporaries_only) {
  const bool earlier_run = !temporaries_only && holds_earlier_run(dir);
  std::vector<fs::path> earlier;
  for (const fs::directory_entry& e : fs::directory_iterator(dir)) {
    // A temporary file of a write (NAME.tmp.PID) is a killed run's, with or without a marker.
    const bool temporary = e.path().filename().string().find(".tmp.") != std::string::npos;
    if (e.is_regular_file() && is_output_name(e.path()) && (earlier_run || temporary))
      earlier.push_back(e.path());
  }
  for (const fs::path& f : earlier) fs::remove(f);
  if (earlier.empty()) return;
  std::sort(earlier.begin(), earlier.end());
  std::string names;  // the first few by name: what was there, not a list of what might be
  for (std::size_t k = 0; k < std::min<std::size_t>(earlier.size(), 4); ++k)
    names += (k ? ", " : "") + earlier[k].filename().string();
  if (earlier.size() > 4) names += " and " + std::to_string(earlier.size() - 4) + " more";
  std::fprintf(stderr, "beampack: note: removed %zu file%s %s from %s: %s\n", earlier.size(),
               plural(static_cast<long long>(earlier.size())),
               earlier_run ? "of an earlier run" : "that a killed run's writes left", dir.c_str(),
               names.c_str());
}

// `--resume DIR` into DIR whose run finished: nothing is left to run. A checkpoint there is a
// periodic one (--checkpoint-every), and resuming it would run the tail again over the results.
// Into another folder such a checkpoint runs again; without one, the refusal says why there is
// none (it said only that DIR/checkpoint.bin could not be read).
void refuse_to_resume_a_finished_run(const fs::path& dir, bool in_place) {
  const nlohmann::json j = summary_in(dir);
  if (!j.is_object() || !j.contains("interrupted") || j["interrupted"] != false ||
      j.contains("failed"))
    return;  // a failed run's periodic checkpoint may be resumed (a disk that was full)
  std::error_code ec;
  const bool periodic = fs::is_regular_file(dir / "checkpoint.bin", ec);
  if (periodic && !in_place) return;
  const int pulses = j.value("pulses", 0);
  throw InputError("--resume " + dir.string() + ": the run there finished (summary.json, " +
                   std::to_string(pulses) + " pulse" + plural(pulses) + "): nothing to resume" +
                   (periodic ? "; to run it again from its last periodic checkpoint, give --out "
                               "another folder"
                             : " (it kept no periodic checkpoint to start again from)"));
}

namespace {

// Files of the pulses before a checkpoint that are not in its folder (deleted to save space, say),
// as a resume's warnings name them: frames and ray path files alike.
struct MissingFiles {
  std::string names;  // "particles_0000.vtp, particles_0003.vtp"
  int count = 0;
  void add(const std::string& name) { names += (count++ > 0 ? ", " : "") + name; }
  // "2 frames of the pulses before the checkpoint are not there (...)", for `kind` = "frame".
  std::string said(const char* kind) const {
    return std::to_string(count) + " " + kind + plural(count) +
           " of the pulses before the checkpoint " + (count == 1 ? "is" : "are") + " not there (" +
           names + ")";
  }
  const char* them() const { return count == 1 ? "it" : "them"; }
  // "beampack: warning: --resume FROM: <said(kind)>; <consequence>" on stderr, if any is missing;
  // `consequence` names them with them().
  void warn(const fs::path& from, const char* kind, const std::string& consequence) const {
    if (count > 0)
      std::fprintf(stderr, "beampack: warning: --resume %s: %s; %s\n", from.c_str(),
                   said(kind).c_str(), consequence.c_str());
  }
};

}  // namespace

// The checkpoint's frames that are no longer in its folder (deleted to save space, say) leave the
// series, with a warning naming them: particles.pvd names no file that is not there.
void drop_missing_frames(const fs::path& from, RunRecord& record) {
  MissingFiles missing;
  std::erase_if(record.frames, [&](const std::pair<std::string, double>& frame) {
    std::error_code ec;
    if (fs::is_regular_file(from / frame.first, ec)) return false;
    missing.add(frame.first);
    return true;
  });
  missing.warn(from, "frame", std::string("particles.pvd leaves ") + missing.them() + " out");
}

// A run resumed into another folder than its checkpoint's continues the frames and ray paths
// of the pulses before the checkpoint, which stay in the checkpoint's folder: copied, so the
// new folder holds the whole series (particles.pvd names every frame).
void carry_earlier_files(const fs::path& from, const fs::path& to, const RunRecord& record,
                         const OutputSpec& output, int pulses_ended) {
  // Through a temporary, as every output file: a copy cut short (a full disk, a second interrupt
  // while a frame of hundreds of MB is copied) leaves no half frame under its name.
  auto carry = [&](const std::string& name) {
    std::error_code ec;
    if (!fs::is_regular_file(from / name, ec)) return false;
    std::ifstream in(from / name, std::ios::binary);
    // Block by block: `o << in.rdbuf()` stops without an error at a write that fails part way.
    write_atomically((to / name).string(), [&](std::ostream& o) {
      std::vector<char> block(1 << 16);
      while (in && o) {
        in.read(block.data(), static_cast<std::streamsize>(block.size()));
        o.write(block.data(), in.gcount());
      }
      if (o && !in.eof()) throw RunError("--resume: cannot read " + (from / name).string());
    });
    return true;
  };
  for (const auto& [name, time] : record.frames) carry(name);  // drop_missing_frames said which
  MissingFiles missing;
  for (int k = 0; output.rays && k < pulses_ended; ++k)
    if (const std::string name = pulse_file("rays", k); !carry(name)) missing.add(name);
  // Deleted to save space, as frames may be: said, as they are.
  missing.warn(from, "ray path file", to.string() + " will not hold " + missing.them());
}

// rays.pvd's series as a resume finds it: the ray path file of each pulse in the history rows
// (`time_s,pulse,...`), at that pulse's end time, where the file is in `dir`. One deleted to save
// space is left out, as its frame is from particles.pvd; `missing` names them.
std::vector<std::pair<std::string, double>> ray_series(const std::string& history,
                                                       const fs::path& dir, MissingFiles& missing) {
  std::vector<std::pair<std::string, double>> series;
  std::istringstream rows(history);
  std::string row;
  std::getline(rows, row);  // the header
  while (std::getline(rows, row)) {
    const std::size_t comma = row.find(',');
    const int pulse = std::atoi(row.c_str() + comma + 1);
    const std::string name = pulse_file("rays", pulse - 1);
    std::error_code ec;
    if (fs::is_regular_file(dir / name, ec)) series.emplace_back(name, std::stod(row));
    else missing.add(name);
  }
  return series;
}

// A resume's rays.pvd: the series so far, in its own folder too (a killed later part's file
// named pulses the results do not hold). None when no ray file is there yet. Missing files are
// said for a resume in place; one into another folder said them as it carried the others.
void rebuild_ray_series(const fs::path& dir, RunRecord& record, bool in_place) {
  MissingFiles missing;
  record.ray_files = ray_series(record.history, dir, missing);
  std::error_code ec;
  if (record.ray_files.empty()) fs::remove(dir / "rays.pvd", ec);
  else write_pvd((dir / "rays.pvd").string(), record.ray_files);
  if (in_place)
    missing.warn(dir, "ray path file", std::string("rays.pvd leaves ") + missing.them() + " out");
}

// The figures at the end of the run's last pulse, or at its start before one ends: what a run that
// fails later still has, whole.
struct PulsesEnded {
  int count = 0;  // in this run (a resumed one: since the checkpoint)
  Figures figures;
  Counts counts;
  PulsesEnded(const Figures& start, const Counts& c) : figures(start), counts(c) {}
  void note(const Figures& f, const Counts& c) { ++count, figures = f, counts = c; }
};

// The pulses that ended, a history row each (the header is the first line).
int history_rows(const RunRecord& record) {
  return static_cast<int>(std::count(record.history.begin(), record.history.end(), '\n')) - 1;
}

// summary.json, the last of a set of writes begun at `writing` (write_atomically fills in order):
// its wall time (`wall_at_writing` and the writes since, left in r) and output stage hold the
// files before it (particles.csv: 0.5 s at 10^6 particles), and leave out only its own few
// kilobytes and the renames. `failed`: {message, time_s} of a failed run, else null.
OutputFile summary_file(const fs::path& out, const Simulation& sim, RunResult& r,
                        const RunConfig& config, RunRecord& record, Clock::time_point writing,
                        double wall_at_writing, nlohmann::json failed) {
  return {(out / "summary.json").string(),
          [&sim, &r = r, &config, &record = record, writing, wall_at_writing,
           failed = std::move(failed)](std::ostream& o) {
    record.stages.output.seconds += seconds_since(writing);
    ++record.stages.output.calls;
    r.wall_seconds = wall_at_writing + seconds_since(writing);  // the stages within it
    nlohmann::json j = summary_json(sim, r, config, record.earlier_parts, record.stages);
    if (!failed.is_null()) j["failed"] = failed;
    o << json_text(j) << '\n';
          }};
}

// A step that throws leaves the particles part way through it, and a run's end may fail to write
// them (a full disk): they are not written (nor a checkpoint), but the pulses the run ended are,
// as history.csv and a summary.json of the last one's end that says what failed. Hours of pulses
// are not lost to one that fails (a beam drawn too narrow in pulse 1361, a step needing more
// sub-steps than allowed). Before any pulse ends the summary is of the run's start: a script
// finds the failure in summary.json either way. `no_particles_because`: why particles.csv is not
// among them; one already in the folder (an interrupt's, which a resume into its folder runs on
// from) is of an earlier time than the failure: it goes.
void keep_pulses_before_failure(const fs::path& out, const Simulation& sim, RunRecord& record,
                                const PulsesEnded& ended, const RunConfig& config,
                                const char* failure, double wall_seconds,
                                const char* no_particles_because) {
  RunResult r;
  r.figures = ended.figures;
  r.counts = ended.counts;
  r.pulses_ended = history_rows(record);
  const double failed_at = sim.figures().time;
  // The output stage holds these writes, as at a run's end (a failure before the first pulse's
  // end had none, and read as a skipped stage without a reason).
  write_atomically({{(out / "history.csv").string(), [&](std::ostream& o) { o << record.history; }},
                    summary_file(out, sim, r, config, record, Clock::now(), wall_seconds,
                                 {{"message", failure}, {"time_s", failed_at}})});
  std::error_code ec;
  fs::remove(out / "particles.csv", ec);
  if (ended.count == 0) {  // a resumed run's history holds the pulses before its checkpoint
    const std::string rows = r.pulses_ended == 0
                                 ? std::string("its header only")
                                 : "the " + std::to_string(r.pulses_ended) + " pulse" +
                                       plural(r.pulses_ended) + " ended before it";
    std::fprintf(stderr,
                 "beampack: the run failed at t = %.6g s, before a pulse of its own ended; %s "
                 "holds summary.json as at its start (t = %.6g s), with the failure, and "
                 "history.csv (%s; no particles.csv: %s)\n",
                 failed_at, out.c_str(), ended.figures.time, rows.c_str(), no_particles_because);
    return;
  }
  std::fprintf(stderr,
               "beampack: the run failed at t = %.6g s, after %d pulse%s had ended; %s holds them "
               "(history.csv, and summary.json as at the last one's end, with the failure; no "
               "particles.csv: %s)\n",
               failed_at, r.pulses_ended, plural(r.pulses_ended), out.c_str(),
               no_particles_because);
}

// keep_pulses_before_failure, or why it could not: the failure itself is what the run reports.
void try_to_keep_pulses(const fs::path& out, const Simulation& sim, RunRecord& record,
                        const PulsesEnded& ended, const RunConfig& config, const char* failure,
                        double wall_seconds, const char* no_particles_because) {
  try {
    keep_pulses_before_failure(out, sim, record, ended, config, failure, wall_seconds,
                               no_particles_because);
  } catch (const std::exception& e) {  // a full disk, say
    std::fprintf(stderr, "beampack: the pulses before the failure could not be written: %s\n",
                 e.what());
  }
}

// --resume: the checkpoint's run file and particles stand in for the run's sources.
void resume_from_checkpoint(const RunOptions& options, bool into_checkpoint_folder,
                            RunRecord& record, std::optional<StateReader>& saved,
                            RunSources& sources) {
  if (!options.sources.file.empty() || !options.sources.preset.empty() ||
      !options.sources.sets.empty())
    throw InputError("--resume " + options.resume +
                     ": the checkpoint holds its run file; give no run file, --preset or --set");
  refuse_to_resume_a_finished_run(options.resume, into_checkpoint_folder);
  saved.emplace(open_checkpoint(fs::path(options.resume) / "checkpoint.bin", record));
  warn_of_another_build(record.earlier_parts.back());
  sources.text = record.config_text;
  sources.saved_packing = [&saved](const SimulationSpec& spec) {
    return Simulation::saved_packing(*saved, spec);
  };
}

// The frame of the state a new run starts from, at its start time, first in particles.pvd: the
// bed before the beam (a resumed run has it from its checkpoint's folder).
void write_start_frame(const Simulation& sim, const fs::path& out, RunRecord& record) {
  const StageTimer timer(record.stages.output);
  write_particles_vtp((out / kStartFrame).string(), sim.particles(), sim.absorbed());
  record.frames.emplace_back(kStartFrame, sim.figures().time);
  write_pvd((out / "particles.pvd").string(), record.frames);
}

// What a pulse end leaves: a history row, the pulse's ray paths and particle frame when asked
// for, the figures a later failure keeps, and whether a checkpoint is due after the step.
void record_pulse_ends(Simulation& sim, const OutputSpec& output, const fs::path& out,
                       RunRecord& record, GrowingFile& history, PulsesEnded& ended,
                       bool& checkpoint_due) {
  sim.on_pulse_end([&sim, &output, out, &record, &history, &ended, &checkpoint_due](int pulse) {
    const StageTimer timer(record.stages.output);
    const Figures figures = sim.figures();  // one pass over the particles per pulse end
    ended.note(figures, sim.counts());
    const std::string row = history_row(figures);
    record.history += row;
    history.append(record.history, row);
    if (output.rays) {
      const std::string name = pulse_file("rays", pulse);
      write_rays_vtp((out / name).string(), sim.take_ray_paths());
      record.ray_files.emplace_back(name, figures.time);
      write_pvd((out / "rays.pvd").string(), record.ray_files);
    }
    if (output.frames) {
      const std::string name = pulse_file("particles", pulse);
      write_particles_vtp((out / name).string(), sim.particles(), sim.absorbed());
      record.frames.emplace_back(name, figures.time);
      write_pvd((out / "particles.pvd").string(), record.frames);
    }
    // |=: several pulses may end in one step (a period shorter than the step), and a later one
    // must not cancel the checkpoint an earlier one made due.
    checkpoint_due |= record.checkpoint_every > 0 && (pulse + 1) % record.checkpoint_every == 0;
  });
}

// Steps until the run is done or interrupted, with a checkpoint between steps when one is due
// (never inside a step: a resume continues with exactly the next step). A step that fails keeps
// the pulses ended before it, and its exception goes on.
void run_steps(Simulation& sim, const RunConfig& config, const fs::path& out, RunRecord& record,
               const PulsesEnded& ended, bool& checkpoint_due, bool quiet,
               Clock::time_point start) {
  try {
    Progress progress(quiet, "");
    while (!sim.done() && !stop_requested().load()) {
      sim.step();
      if (checkpoint_due && !sim.done()) {
        const StageTimer timer(record.stages.output);  // the checkpoint holds the time before it
        write_atomically({checkpoint_file(out / "checkpoint.bin", sim, record,
                                          record.earlier_seconds + seconds_since(start), false)});
        record.spent_checkpoint_here = false;
      }
      checkpoint_due = false;
      progress.update(sim);
    }
  } catch (const std::exception& failure) {
    try_to_keep_pulses(out, sim, record, ended, config, failure.what(),
                       record.earlier_seconds + seconds_since(start),
                       sim.failed() ? "the particles are part way through a step"
                                    : "the run stopped at a pulse's end, writing its files");
    throw;
  }
}

// The run's end, finished or interrupted: its files (and a checkpoint when interrupted), its
// table and its warnings. Returns the exit code. When its files cannot be written, the pulses it
// ended are kept as after a failed step, and the failure goes on.
int finish_run(const Simulation& sim, const RunConfig& config, RunRecord& record,
               const PulsesEnded& ended, const fs::path& out, Clock::time_point start, bool quiet) {
  writing_results.store(sim.done());  // first: an interrupt from here on has no step to stop after
  const struct Written {
    ~Written() { writing_results.store(false); }
  } written;
  const auto writing = Clock::now();  // the output stage's last call: the run's end's files
  RunResult r;
  r.figures = sim.figures();
  r.counts = sim.counts();
  r.interrupted = !sim.done();
  // Seconds of writing (particles.csv: 7.7 s at 10^7 particles) said, as the set-up is.
  if (!quiet && takes_seconds(sim.particles().size(), 0))
    std::fprintf(stderr, "beampack: writing the run's files (particles.csv: %zu particles)\n",
                 sim.particles().size());
  r.pulses_ended = history_rows(record);
  r.wall_seconds = record.earlier_seconds + seconds_since(start);  // like the stage times
  // One set: a full disk leaves the folder as it was, not particles.csv without its summary.
  std::vector<OutputFile> files;
  if (r.interrupted)  // its record of the times ends here, before the files of the end
    files.push_back(checkpoint_file(out / "checkpoint.bin", sim, record, r.wall_seconds, true));
  files.push_back({(out / "history.csv").string(), [&](std::ostream& o) { o << record.history; }});
  files.push_back(particles_csv((out / "particles.csv").string(), sim.particles(), sim.absorbed()));
  // Last, so that it times the others; the table printed after it shows the same times.
  files.push_back(summary_file(
      out, sim, r, config, record, writing,
      record.earlier_seconds + std::chrono::duration<double>(writing - start).count(), nullptr));
  try {
    write_atomically(files);
  } catch (const std::exception& failure) {
    try_to_keep_pulses(out, sim, record, ended, config, failure.what(), r.wall_seconds,
                       "the files of the run's end could not be written");
    throw;
  }
  // A run resumed into its folder from an interrupt's checkpoint, and now finished: that
  // checkpoint is spent (a later --resume would offer it as a periodic one to run again from).
  // Periodic checkpoints (--checkpoint-every) are kept; an interrupt's replaced the last one.
  std::error_code ec;
  if (!r.interrupted && record.spent_checkpoint_here) fs::remove(out / "checkpoint.bin", ec);
  print_table(sim, r, record.stages);
  say_warnings("", sim.run_warnings());
  if (!r.interrupted) return 0;
  const std::string where = r.figures.pulse > 0
                                ? "in pulse " + std::to_string(r.figures.pulse) + " of " +
                                      std::to_string(config.sim.pulses.count)
                                : std::string("before the first pulse");
  std::fprintf(stderr,
               "beampack: interrupted at t = %.6g s %s; outputs in %s hold that state "
               "(history.csv: the pulses before it); continue with: beampack run --resume %s\n",
               r.figures.time, where.c_str(), out.c_str(), out.c_str());
  return interrupted_exit_code();
}

int run_command(const RunOptions& options) {
  note_reading_input();
  RunRecord record;
  std::optional<StateReader> saved;
  RunSources sources = options.sources;
  const std::string out_dir =
      options.resume.empty() || options.out_set ? options.out_dir : options.resume;
  std::error_code same_ec;
  const bool into_checkpoint_folder =
      !options.resume.empty() && fs::equivalent(out_dir, options.resume, same_ec);
  // Locked before anything there is read: a resume in place waited for the run it resumes and
  // then read the checkpoint that run had replaced, or removed. A folder resumed into another is
  // read under a shared lock until its files are copied.
  const OutDir out_folder(out_dir);
  std::optional<FolderLock> reading;
  if (!options.resume.empty() && !into_checkpoint_folder)
    reading.emplace(options.resume, FolderLock::Mode::shared, "--resume");
  if (!options.resume.empty())
    resume_from_checkpoint(options, into_checkpoint_folder, record, saved, sources);
  RunConfig config = load_run_config(sources);
  warn_of_input({&config});
  say_warnings("", spec_warnings(config.sim));
  if (options.resume.empty()) record.config_text = toml_text(config.resolved);
  if (options.resume.empty() || options.checkpoint_set)
    record.checkpoint_every = options.checkpoint_every;
  refuse_outputs_over_inputs(
      out_dir, {{"the run file", sources.file}, {"packing.file", config.sim.packing.file}});
  refuse_non_files_at_outputs(out_dir, is_output_name);
  const auto threads = limit_threads(options.threads);
  const auto start = Clock::now();
  const bool resumed = saved.has_value();
  const std::unique_ptr<Simulation> owned =
      set_up_unless_interrupted(config, options.quiet, "", std::move(saved));
  if (!owned) {  // nothing written yet: out_folder removes the folders this run made
    std::fprintf(stderr, "beampack: interrupted during set-up; nothing written\n");
    return interrupted_exit_code();
  }
  config.packing.reset();  // the simulation holds its own copy
  Simulation& sim = *owned;
  say_warnings("", sim.scene_warnings());  // of a resumed run, of the state restored
  record.spent_checkpoint_here &= into_checkpoint_folder;
  // Only once the inputs are read whole: a run refused for bad input leaves the folder as it was.
  remove_earlier_run(out_dir, into_checkpoint_folder);
  if (resumed) drop_missing_frames(options.resume, record);
  const double output_before = record.stages.output.seconds;
  if (resumed && (!into_checkpoint_folder || !record.frames.empty())) {
    const StageTimer timer(record.stages.output);  // the earlier pulses' files
    if (!into_checkpoint_folder)
      carry_earlier_files(options.resume, out_dir, record, config.output,
                          std::max(sim.figures().pulse - 1, 0));
    if (!record.frames.empty())  // the series as it now stands, before any new frame
      write_pvd((fs::path(out_dir) / "particles.pvd").string(), record.frames);
  }
  if (resumed && config.output.rays) {
    const StageTimer timer(record.stages.output);
    rebuild_ray_series(out_dir, record, into_checkpoint_folder);
  }
  reading.reset();  // the folder resumed from is read, and free for others
  sim.record_ray_paths(config.output.rays);
  const fs::path out(out_dir);
  if (!resumed && config.output.frames) write_start_frame(sim, out, record);
  bool checkpoint_due = false;
  PulsesEnded ended(sim.figures(), sim.counts());
  GrowingFile history((out / "history.csv").string());  // a row as each pulse ends
  record_pulse_ends(sim, config.output, out, record, history, ended, checkpoint_due);
  count_set_up(record.stages.setup, sim, resumed,
               seconds_since(start) - (record.stages.output.seconds - output_before));
  run_steps(sim, config, out, record, ended, checkpoint_due, options.quiet, start);
  return finish_run(sim, config, record, ended, out, start, options.quiet);
}

}  // namespace beampack::tools

namespace beampack::tools {

// output.frames and output.rays are files of one run; sweep and converge write their tables only.
void refuse_run_only_outputs(const RunConfig& config, const char* command) {
  if (config.output.frames || config.output.rays)
    throw InputError(std::string("`output.") + (config.output.frames ? "frames" : "rays") +
                     "` = true: written by `beampack run` only; `beampack " + command +
                     "` writes its table and chart");
}

namespace {

// A swept value as a CSV cell (RFC 4180): one holding a quote, a comma or a line break is quoted,
// its quotes doubled (`pk/e"f.xyz` made the row unreadable).
std::string csv_cell(const std::string& value) {
  if (value.find_first_of("\",\r\n") == std::string::npos) return value;
  std::string out = "\"";
  for (const char c : value) out += c == '"' ? std::string("\"\"") : std::string(1, c);
  return out + '"';
}

// The cells after the first of a CSV row with the header's columns, all empty: ",,,...".
std::string empty_cells(const std::string& header) {
  return std::string(static_cast<std::size_t>(std::count(header.begin(), header.end(), ',')), ',');
}

}  // namespace

namespace {

// --values at its commas, but not at one inside a TOML string or array: `"z-,x+",y-` is two
// values (a multi-face thermal.walls could not be swept). A trailing comma leaves an empty value.
std::vector<std::string> split_values(const std::string& arg) {
  std::vector<std::string> items(1);
  char quote = 0;
  int depth = 0;
  for (const char c : arg) {
    if (quote == 0 && c == ',' && depth == 0) {
      items.emplace_back();
      continue;
    }
    if (quote != 0 && c == quote) quote = 0;
    else if (quote == 0 && (c == '"' || c == '\'')) quote = c;
    else if (quote == 0 && (c == '[' || c == '{')) ++depth;
    else if (quote == 0 && (c == ']' || c == '}') && depth > 0) --depth;
    items.back() += c;
  }
  return items;
}

}  // namespace

namespace {

// A swept value's number as the run reads it, TOML's (1_00 is 100, 0x10 is 16: strtod stopped at
// the `_` and made `1_00` a word); none for a word, a string, a boolean, an array or a table.
std::optional<double> numeric_meaning(const std::string& value) {
  try {
    const toml::table t = parsed_value(value, "--values");
    if (const auto* i = t.get_as<std::int64_t>("v")) return double(i->get());
    if (const auto* d = t.get_as<double>("v")) return d->get();
  } catch (const std::runtime_error&) {  // a bare word: the run reads it as a string
  }
  return std::nullopt;
}

// What a swept value means to the run, to find one given twice: 100 and 1e2 are one number,
// `"flat"` and `flat` one word.
std::string meaning_of(const std::string& value) {
  if (const std::optional<double> x = numeric_meaning(value)) return "number " + exact(*x);
  try {
    const toml::table t = parsed_value(value, "--values");
    if (const auto* text = t.get_as<std::string>("v")) return "text " + text->get();
  } catch (const std::runtime_error&) {
    return "text " + value;
  }
  return "value " + value;
}

// A value given twice would be run twice and drawn as one point (`--values 1,1`).
void refuse_repeated_values(const std::vector<std::string>& values) {
  for (std::size_t k = 1; k < values.size(); ++k)
    for (std::size_t j = 0; j < k; ++j)
      if (meaning_of(values[k]) == meaning_of(values[j]))
        throw InputError("--values: value " + std::to_string(k + 1) + " (" + values[k] +
                         ") repeats value " + std::to_string(j + 1) + " (" + values[j] +
                         "): give each value once");
}

// Whether a --set gives the swept key: `material.conductivity=3`, or a table holding it,
// `material={conductivity=5}` (--values would override it without a word). A --set that does
// not read is left to the run's own message.
bool sets_swept_key(const std::string& set, const std::string& param) {
  const std::string key = assignment_key(set);
  if (key == param) return true;
  if (!param.starts_with(key + ".")) return false;  // in a table `key`, if anywhere
  Params p;
  try {
    p.merge_assignment(set);
  } catch (const InputError&) {
    return false;
  }
  return p.has(param);
}

}  // namespace

// The swept values, trimmed; an empty one ("1,,2", a stray comma) or a repeated one is refused,
// not dropped, and so is a --set of the swept key (--values would override it without a word).
std::vector<std::string> sweep_values(const SweepOptions& options, const std::string& param) {
  std::vector<std::string> items;
  for (const std::string& arg : options.values) {
    const std::vector<std::string> split = split_values(arg);
    items.insert(items.end(), split.begin(), split.end());
  }
  std::vector<std::string> values;
  for (const std::string& item : items) {
    const std::string v = trimmed(item);
    if (v.empty())
      throw InputError("--values: value " + std::to_string(values.size() + 1) + " is empty");
    values.push_back(v);
  }
  if (values.empty()) throw InputError("--values: give at least one value");
  refuse_repeated_values(values);
  if (param.find('=') != std::string::npos)
    throw InputError("--param " + param +
                     ": give the key alone (--param material.conductivity); its values come "
                     "from --values");
  for (const std::string& s : options.run.sources.sets) {
    if (assignment_key(s) == param)
      throw InputError("--set " + s + ": `" + param +
                       "` is the swept --param; its values come from --values");
    if (sets_swept_key(s, param))  // within a table
      throw InputError("--set " + s + ": sets `" + param +
                       "`, the swept --param; its values come from --values");
  }
  return values;
}

namespace {

// Where each value sits on sweep.svg's x axis: its number, or for a sweep of words (any value
// not a number, `beam.profile`) its place 0, 1, 2, ... with the words as labels.
struct SweepAxis {
  std::vector<double> x;
  bool named = false;
};

SweepAxis sweep_axis(const std::vector<std::string>& values) {
  SweepAxis a;
  for (std::size_t k = 0; k < values.size(); ++k) {
    const std::optional<double> x = numeric_meaning(values[k]);
    a.named |= !x || !std::isfinite(*x);  // nan, inf: no place on an axis
    a.x.push_back(x.value_or(0.0));
  }
  if (a.named)
    for (std::size_t k = 0; k < values.size(); ++k) a.x[k] = double(k);
  return a;
}

// sweep.svg. The line joins numbers in their order on the axis (`--values 100,0,50` drew a
// zig-zag), words in the order given. Values > 0 spanning two decades or more (optics.cutoff
// 1e-14..1e-10, beam.rays 100..1e5) get a log axis: on a linear one all but the largest crowd
// onto 0.
Chart sweep_chart(const std::string& param, const std::vector<std::string>& values,
                  const SweepAxis& axis, Series vv) {
  bool log_x = false;
  if (!axis.named) {
    std::vector<std::size_t> order(vv.x.size());
    for (std::size_t k = 0; k < order.size(); ++k) order[k] = k;
    std::stable_sort(order.begin(), order.end(),
                     [&](std::size_t a, std::size_t b) { return vv.x[a] < vv.x[b]; });
    Series sorted{vv.label, {}, {}};
    for (std::size_t k : order) sorted.x.push_back(vv.x[k]), sorted.y.push_back(vv.y[k]);
    vv = sorted;
    log_x = !vv.x.empty() && vv.x.front() > 0 && vv.x.back() >= 100 * vv.x.front();
  }
  return Chart{"vaporized fraction against " + param,
               param + (log_x ? " (log scale)" : ""),
               "vaporized fraction",
               log_x,
               false,
               {vv},
               axis.named ? values : std::vector<std::string>{}};
}

}  // namespace

int sweep_command(const SweepOptions& options) {
  note_reading_input();
  const std::string param = trimmed(options.param);  // `--param ' k'` wrote a header " k,..."
  const std::vector<std::string> values = sweep_values(options, param);
  const OutDir out_folder(options.run.out_dir);
  const auto threads = limit_threads(options.run.threads);
  // Resolve every configuration first: a bad value fails before any run starts.
  std::vector<RunConfig> configs;
  RunSources once = options.run.sources;
  once.read_once();  // every value reads the same run file: a pipe's bytes come only once
  for (const std::string& value : values) {
    RunSources sources = once;
    sources.swept = param + "=" + value;
    sources.swept_origin = "--param " + param + " --values " + value;
    configs.push_back(load_run_config(sources));
    configs.back()
        .packing.reset();  // each value reads its packing when it runs: one copy at a time
    refuse_run_only_outputs(configs.back(), "sweep");
  }
  std::vector<const RunConfig*> resolved;
  for (const RunConfig& c : configs) resolved.push_back(&c);
  warn_of_input(resolved);
  const std::set<std::string> said = warn_of_shared_specs(resolved);
  const fs::path out(options.run.out_dir);
  const std::vector<std::string> tables = {"sweep.csv", "sweep.svg"};
  refuse_non_files_at_outputs(out, tables);
  const std::string header =
      param + ',' + kFigureColumns + ",steps,wall_seconds," + stage_columns();
  std::string csv = header + '\n';
  Series vv{"vaporized fraction", {}, {}};
  const SweepAxis axis = sweep_axis(values);
  const auto start = Clock::now();
  std::vector<LabelledRun> ran;  // the values that ran to their end, for the stage table
  int code = 0;  // a value that fails leaves its row empty; the others still run and are written
  bool cut = false;  // an interrupt left values out (one after the last value ends leaves none)
  for (std::size_t k = 0; k < configs.size(); ++k) {
    const std::string label = "sweep " + param + " = " + values[k] + ": ";
    RunResult r;
    try {
      r = run_scene(configs[k], options.run.quiet, label, said);
    } catch (const std::exception& e) {
      code = std::max(code, report_failed_run(label, e, "its row in sweep.csv is empty"));
      csv += csv_cell(values[k]) + empty_cells(header) + '\n';
      continue;
    }
    if (r.interrupted) {
      cut = true;
      if (!vv.x.empty())
        std::fprintf(stderr,
                     "beampack: sweep interrupted during %s = %s: that value and the rest are not "
                     "in sweep.csv\n",
                     param.c_str(), values[k].c_str());
      else  // the --out folder the sweep made goes
        say_nothing_written(
            "sweep interrupted during " + param + " = " + values[k] + ": no value ran to its end",
            out, tables);
      break;
    }
    const Figures& f = r.figures;
    csv += csv_cell(values[k]) + ',' + figure_columns(f) + ',' + std::to_string(r.counts.steps) +
           ',' + exact(r.wall_seconds) + ',' + stage_cells(r.stages) + '\n';
    vv.x.push_back(axis.x[k]);
    vv.y.push_back(f.vaporized_fraction);
    ran.push_back({param + " = " + values[k], std::move(r.stages), r.counts});
    std::printf("%-24s %s = %-10s v_v = %.4f  melted = %.4f  T_max = %s  (%.2f s)\n", "sweep",
                param.c_str(), values[k].c_str(), f.vaporized_fraction, f.melted_fraction,
                peak_text(f, "%.0f K").c_str(), r.wall_seconds);
    std::fflush(stdout);
    say_warnings(label, r.run_warnings);  // after its line, as `run` says them after its table
  }
  if (vv.x.empty()) {  // a table of only failed values' empty rows is no result
    if (!cut) say_nothing_written("sweep: every value failed", out, tables);
    return cut && code == 0 ? interrupted_exit_code() : code;
  }
  const Chart chart = sweep_chart(param, values, axis, vv);
  StageTime output;
  {
    const StageTimer timer(output);
    write_atomically(
        {{(out / "sweep.csv").string(), [&](std::ostream& o) { o << csv; }},
         {(out / "sweep.svg").string(), [&](std::ostream& o) { o << render_svg(chart); }}});
  }
  for (const std::string& line : stage_total_lines(ran, output)) std::printf("%s\n", line.c_str());
  const double total = seconds_since(start);
  std::printf("sweep: %zu run%s in %.2f s; %s/sweep.csv, %s/sweep.svg\n", vv.x.size(),
              plural(static_cast<long long>(vv.x.size())), total, options.run.out_dir.c_str(),
              options.run.out_dir.c_str());
  return cut && code == 0 ? interrupted_exit_code() : code;
}

}  // namespace beampack::tools
