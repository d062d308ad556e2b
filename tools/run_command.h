#pragma once
// `beampack run` and `beampack sweep`: a scene from a run file, its outputs in a directory.
#include <tbb/global_control.h>

#include <atomic>
#include <chrono>
#include <exception>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "engine/state_io.h"
#include "tools/run_config.h"

namespace beampack::tools {

struct RunOptions {
  RunSources sources;
  std::string out_dir = "beampack-out";
  int threads = 0;  // 0: all cores
  bool quiet = false;
  int checkpoint_every = 0;  // pulses between checkpoints (0: none; Ctrl-C always writes one)
  bool checkpoint_set =
      false;             // --checkpoint-every given (a resume otherwise keeps the checkpoint's)
  std::string resume;    // directory holding checkpoint.bin
  bool out_set = false;  // --out given (a resume otherwise writes into its own directory)
};

// The flag Ctrl-C sets: runs stop after the current step and write what they have.
std::atomic<bool>& stop_requested();
// SIGINT, SIGTERM and SIGHUP stop a run after its step; SIGQUIT quits at once, leaving no
// temporary file (SIGHUP and SIGQUIT only when not ignored: `nohup` keeps a run going).
// Installed before the command line is read: one arriving that early stops a run, sweep or
// converge before its first step, not by the signal.
void install_interrupt_handler();
// Descriptors 0-2 that the caller closed are held open on /dev/null, so no file the run writes
// takes their place (an interrupt note written to stderr would land in it). True when standard
// output was closed: what is printed there is lost, and the command says so.
bool keep_standard_streams_open();

// The simulation of `config`, set up on a worker thread while this one watches stop_requested():
// a set-up of millions of particles takes seconds and writes nothing, so Ctrl-C during it ends
// it at once instead of after it. Null when interrupted; the set-up is then left running, and
// the command's exit_code ends the process. A set-up of seconds is announced on stderr, after
// `label`, unless `quiet`, once the particles are counted and the memory check passes. A resumed
// run's `state` is restored as part of the set-up: what "set up in" times includes it, and an
// interrupt ends its restoring as it ends the rest.
std::unique_ptr<Simulation> set_up_unless_interrupted(const RunConfig& config, bool quiet,
                                                      const std::string& label = "",
                                                      std::optional<StateReader> state = {});
// A command that sets up runs calls this before it reads its input: an interrupt then says that
// the run ends once the read does (it is not cut short), not "after the current step".
void note_reading_input();
// `code`, for main to return; when an interrupted set-up is still running on its thread, the
// process ends here instead, with `code`, once stdout and stderr are flushed: the static
// destructors (TBB's, Embree's) must not run under that thread.
int exit_code(int code);
// The exit code of a command an interrupt stopped before its end: 128 + the signal's number, as a
// shell reports a process the signal ended (130 for Ctrl-C, 143 for SIGTERM), so that a script
// tells "interrupted: --resume goes on" from "failed" (1) and "bad input" (2). A command that
// failed as well returns 1.
int interrupted_exit_code();

// When a run's progress shows: not before two seconds, then at most every half second on a
// terminal (the line rewritten in place) and every 30 s into a file or a pipe (a batch job's log:
// whole lines, which a log of a day's run can hold; a line rewritten twice a second wrote 170,000
// carriage returns there). `last_shown`: when it last showed, none before.
bool progress_due(double elapsed, std::optional<double> last_shown, bool terminal);
// A progress line's text as written: "\r" before it and blanks after on a terminal (over a longer
// line before it), a newline after in a log.
std::string progress_text(const std::string& line, bool terminal);

// The wall time a run has left, by the pace of its pulse launches: the progress line's estimate.
// The pace is measured from the first launch this process sees to the latest (observed at every
// step); the pulse under way is taken to be as far along as the time since its launch says. No
// estimate (NaN) before two launches have been seen.
class PulsePace {
 public:
  // `launched`: pulses launched so far (the pulse under way), at `elapsed` wall seconds.
  void observe(int launched, double elapsed);
  double seconds_left(int count, double elapsed) const;

 private:
  int first_ = -1, latest_ = -1;  // launches counted at the first and the latest change seen
  double first_at_ = 0, latest_at_ = 0;
};

// What a checkpoint holds besides the simulation: the wall time of the runs before it, its
// --checkpoint-every and its frames (file name, time). A checkpoint edited by hand with its
// checksum recomputed could hold a NaN or negative wall time, or a frame named outside the run's
// folder (`../../x.vtp`, which a resume would copy): InputError naming `source`.
void check_checkpoint_record(double earlier_seconds, int checkpoint_every,
                             const std::vector<std::pair<std::string, double>>& frames,
                             const std::string& source);
// InputError naming `source` unless a checkpoint's set-up and output times so far (format 7) are
// finite and >= 0.
void check_checkpoint_stage_times(double setup_seconds, double output_seconds,
                                  const std::string& source);
// InputError naming `source` unless a checkpoint's history rows are text (printable ASCII lines,
// as history.csv is written): a byte edited into them went into history.csv as it was.
void check_history_text(const std::string& history, const std::string& source);

// Runs one scene and writes summary.json, particles.csv, history.csv (and frames). Returns the
// exit code: 0 done, 1 failed, interrupted_exit_code() interrupted.
int run_command(const RunOptions& options);

struct SweepOptions {
  RunOptions run;
  std::string param;
  std::vector<std::string> values;
};
int sweep_command(const SweepOptions& options);

// Adds the time from its making to its end to a stage, and one call.
class StageTimer {
 public:
  explicit StageTimer(StageTime& stage) : stage_(stage) {}
  StageTimer(const StageTimer&) = delete;
  StageTimer& operator=(const StageTimer&) = delete;
  ~StageTimer();

 private:
  StageTime& stage_;
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
};

// A run's stages in the order they run, each with its time, its calls and why it never ran.
using StageTable = std::vector<std::pair<std::string, StageTime>>;

// The result of one finished run, for sweeps and convergence studies.
struct RunResult {
  Figures figures;
  Counts counts;
  double wall_seconds = 0;
  std::vector<double> temperature;
  std::vector<std::uint8_t> alive;  // per particle, 0 once vaporised
  bool interrupted = false;
  int pulses_ended = 0;  // the rows of history.csv; `figures.pulse` counts one still in flight
  std::vector<std::string> run_warnings;  // of a run that ended, for its caller to say after it
  // `setup`, then the simulation's stages (a run of a sweep writes no files of its own).
  StageTable stages;
};
// A lock on a folder (flock on the folder itself, so no lock file is left; the system drops it when
// the process ends, however it ends), exclusive for a command's --out, shared for a folder a
// resume reads from. A holder of the other kind is given a second to let go; then InputError
// naming `option` (--out, --resume) and the folder. A folder that cannot be opened for reading
// (mode 300) or locked at all (some network file systems) is used unlocked.
class FolderLock {
 public:
  enum class Mode { exclusive, shared };
  FolderLock(const std::string& dir, Mode mode, const std::string& option);
  ~FolderLock();
  FolderLock(const FolderLock&) = delete;
  FolderLock& operator=(const FolderLock&) = delete;

 private:
  int fd_ = -1;
};

// A command's --out folder, made (with any missing parents) and checked writable at once, so an
// unusable --out fails before any run. When the command leaves the folders it made empty (bad
// input found while the runs are set up, an interrupted set-up), they are removed again: no empty
// folder is left behind. While it lives the folder is locked (FolderLock, exclusive): a second
// command with the same --out is refused before it removes or writes anything.
class OutDir {
 public:
  explicit OutDir(const std::string& dir);  // InputError naming --out when not creatable or
                                            // writable, or locked by another command
  ~OutDir();
  OutDir(const OutDir&) = delete;
  OutDir& operator=(const OutDir&) = delete;

 private:
  void remove_empty_made();
  std::vector<std::filesystem::path> made_;  // every folder made here, in the order made
  std::optional<FolderLock> lock_;
};
// A run of a sweep or converge that threw: one line on stderr naming `label`, the error and
// `consequence`; returns the exit code it calls for (2 bad input, 1 a failed run).
int report_failed_run(const std::string& label, const std::exception& e, const char* consequence);
// InputError (before the first run) when an entry of `dir` that `is_output` names, where the
// command will write a file, is a folder or another non-file: the final rename would fail after
// the whole run. Symbolic links pass: a rename replaces the link.
void refuse_non_files_at_outputs(
    const std::filesystem::path& dir,
    const std::function<bool(const std::filesystem::path&)>& is_output);
// The same for a command whose files are `names` (sweep's and converge's tables).
void refuse_non_files_at_outputs(const std::filesystem::path& dir,
                                 const std::vector<std::string>& names);
// A sweep or converge with no result (no run ended: every one failed, or an interrupt came before
// one ended) writes no table: "beampack: WHAT: nothing written" on stderr, with a note when the
// tables `names` in `dir` are an earlier run's, left as they were.
void say_nothing_written(const std::string& what, const std::filesystem::path& dir,
                         const std::vector<std::string>& names);
// InputError when a sweep or converge run file asks for output.frames or output.rays.
void refuse_run_only_outputs(const RunConfig& config, const char* command);

// Caps TBB's worker threads while the returned object lives (threads <= 0: no cap). Results do
// not depend on it; only the wall time does.
std::unique_ptr<tbb::global_control> limit_threads(int threads);

// The spec warnings of a sweep's or converge's runs, before the first run: those every run gives
// are said once, as `run` says them, and returned, for run_scene to leave out.
std::set<std::string> warn_of_shared_specs(const std::vector<const RunConfig*>& configs);
// Warnings on stderr, each after `label`, the value or rung of a sweep or converge they belong to
// (as its failures are): "beampack: sweep K = 400: warning: ...".
void say_warnings(const std::string& label, const std::vector<std::string>& warnings);
// One run of a sweep or converge, its warnings on stderr after `label` (the value or rung): its
// spec's but those `said` before, and its scene's once set up; its run's, once it ended, are
// returned (`run_warnings`), for the caller to say after the run's own line.
RunResult run_scene(const RunConfig& config, bool quiet, const std::string& label = "",
                    const std::set<std::string>& said = {});

// sweep.csv's and convergence.csv's stage columns, "setup_s,trace_s,...,rebuild_s", and a run's
// cells for them: its seconds in each stage, 0 in one it skipped (where its time went, beside
// its wall seconds).
std::string stage_columns();
std::string stage_cells(const StageTable& stages);

// One finished run of a sweep or converge, as its stage table counts it: its label (the value or
// rung its lines name), its stages and its counts.
struct LabelledRun {
  std::string label;
  StageTable stages;
  Counts counts;
};
// The stage table of a sweep or converge, as `run` prints its own: each stage's seconds and calls
// summed over `runs`, then the command's own `output` (its tables). A stage that some or all runs
// skipped says in which and why: "skipped in 2 of 5 runs: <why> (K = 0, K = 10)".
std::vector<std::string> stage_total_lines(const std::vector<LabelledRun>& runs,
                                           const StageTime& output);

}  // namespace beampack::tools
