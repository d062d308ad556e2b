// What a run reports beyond its figures: the warning when a ledger is open, and the charts.
#include <gtest/gtest.h>

#include <unistd.h>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <regex>

#include "geometry/error.h"
#include "tests/expect_error.h"
#include "tests/quick_scene.h"
#include "tests/svg_texts.h"
#include "tests/test_dirs.h"
#include "tools/converge.h"
#include "tools/quit_cleanup.h"
#include "tools/run_command.h"
#include "tools/run_config.h"
#include "tools/svg_plot.h"
#include "tools/writers.h"

namespace beampack::tools {
namespace {

// The relative imbalances the table prints: over the energy moved, whatever its size. A floor of
// 1e-300 J under it made a subnormal run's open ledger (5.06e-309 J absorbed, none stored) read
// as 5e-9 while the warning said 1.
TEST(RunReport, RelativeImbalancesHoldForSubnormalEnergies) {
  EnergyLedger e;
  e.injected = 5.561269e-309;
  e.absorbed = 5.055281e-309;
  e.escaped = e.injected - e.absorbed;
  EXPECT_EQ(e.relative_heat_imbalance(), 1.0);
  EXPECT_EQ(e.heat_error(), 1.0);
  EXPECT_EQ(e.relative_optics_imbalance(), 0.0);
  e.stored = 2 * e.absorbed;  // more out than in: -a over the larger side, 2a
  EXPECT_EQ(e.relative_heat_imbalance(), -0.5);
  EXPECT_EQ(EnergyLedger{}.relative_heat_imbalance(), 0.0);  // nothing moved, nothing open
}

EnergyLedger closed_ledger() {
  EnergyLedger e;
  e.injected = 1.0, e.absorbed = 0.6, e.escaped = 0.3, e.cutoff = 0.1;
  e.stored = 0.5, e.vaporized = 0.1;
  return e;
}

// Progress shows after two seconds, then every half second on a terminal, rewritten in place,
// and every 30 s into a log as whole lines (no carriage return there).
TEST(RunReport, ProgressIsPacedForATerminalOrALog) {
  for (const bool terminal : {true, false}) {
    EXPECT_FALSE(progress_due(1.99, std::nullopt, terminal));
    EXPECT_TRUE(progress_due(2.0, std::nullopt, terminal));
  }
  EXPECT_FALSE(progress_due(2.4, 2.0, true));
  EXPECT_TRUE(progress_due(2.5, 2.0, true));
  EXPECT_FALSE(progress_due(31.9, 2.0, false));
  EXPECT_TRUE(progress_due(32.0, 2.0, false));
  EXPECT_EQ(progress_text("pulse 3/5", true), "\rpulse 3/5   ");
  EXPECT_EQ(progress_text("pulse 3/5", false), "pulse 3/5\n");
}

// The progress line's time left: the pace of the launches seen (none before two), the pulse under
// way as far along as the time since its launch, never below zero.
TEST(RunReport, PulsePaceGivesTheTimeLeftFromTheLaunchesSeen) {
  PulsePace pace;
  pace.observe(1, 2.0);  // pulse 1 under way, launched at a time not seen
  EXPECT_TRUE(std::isnan(pace.seconds_left(10, 2.0)));
  pace.observe(1, 2.5);
  pace.observe(2, 3.0);  // one launch seen: no pace yet
  EXPECT_TRUE(std::isnan(pace.seconds_left(10, 3.0)));
  pace.observe(4, 5.0);                               // two pulses in 2 s
  EXPECT_DOUBLE_EQ(pace.seconds_left(10, 5.5), 6.5);  // pulses 4-10 at 1 s, 4 half done
  pace.observe(10, 11.0);                             // eight pulses in 8 s
  EXPECT_DOUBLE_EQ(pace.seconds_left(10, 11.25), 0.75);
  EXPECT_EQ(pace.seconds_left(10, 20.0), 0.0);  // overdue
}

// What a checkpoint holds besides the simulation is checked as it is read: edited by hand, with
// its checksum recomputed, it gave summary.json a null wall time, particles.pvd a "nan" time,
// and a resume copied a frame named ../../src.vtp from outside the folder to outside the other.
TEST(RunReport, ACheckpointsRunRecordIsCheckedAsItIsRead) {
  using Frames = std::vector<std::pair<std::string, double>>;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  auto message = [](double wall, int every, const Frames& frames) {
    return testing::error_message<InputError>(
        [&] { check_checkpoint_record(wall, every, frames, "ck.bin"); });
  };
  EXPECT_EQ(message(12.5, 2,
                    {{"particles_0000.vtp", 0.0},
                     {"particles_0001.vtp", 1e-12},
                     {"particles_10000.vtp", 2e-12}}),  // pulse_file's names past 9999 pulses
            testing::kAccepted);
  EXPECT_EQ(message(0.0, 0, {}), testing::kAccepted);
  for (double wall : {nan, -5.0, std::numeric_limits<double>::infinity()})
    EXPECT_CONTAINS(message(wall, 0, {}), "ck.bin: its wall time so far");
  EXPECT_CONTAINS(message(1.0, -1, {}), "--checkpoint-every");
  for (const char* name : {"../../src.vtp", "/etc/x.vtp", "particles_00a1.vtp", "particles_.vtp",
                           "particles_0001.vtp/..", "rays_0001.vtp"})
    EXPECT_CONTAINS(message(1.0, 0, {{name, 0.0}}), "not particles_NNNN.vtp") << name;
  EXPECT_CONTAINS(message(1.0, 0, {{"particles_0003.vtp", nan}}), "not finite");
}

// Format 7's set-up and output times so far are checked as the wall time is: summary.json would
// show a NaN or negative stage.
TEST(RunReport, ACheckpointsSetUpAndOutputTimesAreChecked) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  EXPECT_NO_THROW(check_checkpoint_stage_times(0.0, 0.0, "ck.bin"));
  EXPECT_NO_THROW(check_checkpoint_stage_times(1.5, 0.25, "ck.bin"));
  for (double bad : {nan, -1.0, inf}) {
    testing::expect_error<InputError>([&] { check_checkpoint_stage_times(bad, 0.0, "ck.bin"); },
                                      "ck.bin: its set-up time so far");
    testing::expect_error<InputError>([&] { check_checkpoint_stage_times(0.0, bad, "ck.bin"); },
                                      "ck.bin: its output time so far");
  }
}

// The history rows a checkpoint carries into history.csv are printable text: a byte edited into
// them (the checksum recomputed) went into history.csv as it was, invalid UTF-8 and all.
TEST(RunReport, ACheckpointsHistoryRowsAreText) {
  EXPECT_NO_THROW(check_history_text("time_s,pulse\n1e-12,1\n", "ck.bin"));
  for (const std::string& bad :
       {std::string("1e-12,\xFF\n"), std::string("1e-12,1\0\n", 8), std::string("1e-12\r\n")}) {
    SCOPED_TRACE(bad);
    testing::expect_error<InputError>([&] { check_history_text(bad, "ck.bin"); },
                                      "ck.bin: its history rows hold byte \\x");
  }
}

// An output file is written beside itself and renamed into place; a fill that throws (an error or
// an interrupt mid-write) leaves neither the file nor its temporary behind.
TEST(RunReport, AWriteThatThrowsLeavesNoFileBehind) {
  const auto dir = beampack::testing::process_dir() / "throwing_write";
  std::filesystem::create_directories(dir);
  const auto path = dir / "summary.json";
  EXPECT_THROW(write_atomically(
                   path.string(),
                   [](std::ostream& o) {
    o << "half";
    throw std::runtime_error("stopped");
                   }),
               std::runtime_error);
  EXPECT_TRUE(std::filesystem::is_empty(dir)) << "a temporary file was left in " << dir;
}

// A set of files that belong together is renamed into place only once every one is whole: a
// failure writing the last (a full disk) leaves the earlier ones as they were, not replaced by
// this run's, and no temporary behind.
TEST(RunReport, ASetOfFilesIsReplacedWholeOrNotAtAll) {
  namespace fs = std::filesystem;
  const auto dir = beampack::testing::process_dir() / "file_set";
  fs::remove_all(dir);
  fs::create_directories(dir);
  const auto read = [](const fs::path& p) {
    std::ifstream in(p);
    return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  };
  write_atomically(
      {{(dir / "particles.csv").string(), [](std::ostream& o) { o << "old particles"; }},
       {(dir / "summary.json").string(), [](std::ostream& o) { o << "old summary"; }}});
  const auto fail_last = [&] {
    write_atomically(
        {{(dir / "particles.csv").string(), [](std::ostream& o) { o << "new particles"; }},
         {(dir / "summary.json").string(), [](std::ostream& o) {
            o << "new";
            throw RunError("disk full");
          }}});
  };
  EXPECT_THROW(fail_last(), RunError);
  EXPECT_EQ(read(dir / "particles.csv"), "old particles");
  EXPECT_EQ(read(dir / "summary.json"), "old summary");
  EXPECT_EQ(std::distance(fs::directory_iterator(dir), fs::directory_iterator()), 2)
      << "a temporary file was left in " << dir;
  write_atomically(
      {{(dir / "particles.csv").string(), [](std::ostream& o) { o << "new particles"; }},
       {(dir / "summary.json").string(), [](std::ostream& o) { o << "new summary"; }}});
  EXPECT_EQ(read(dir / "particles.csv"), "new particles");
  EXPECT_EQ(read(dir / "summary.json"), "new summary");
}

// What a second interrupt removes, with no destructor to run: the temporary files being written
// (only names ending as this process's temporaries) and the folders the command made, innermost
// first, while they are empty.
TEST(RunReport, AQuitRemovesTemporariesAndEmptyMadeFolders) {
  namespace fs = std::filesystem;
  const auto dir = beampack::testing::process_dir() / "quit_cleanup";
  fs::remove_all(dir);
  const fs::path outer = dir / "a", inner = outer / "b", kept = dir / "kept";
  fs::create_directories(inner);
  fs::create_directories(kept);
  const auto touch = [](const fs::path& p) { std::ofstream(p) << "x"; };
  const std::string temporary = temporary_path((kept / "summary.json").string());
  ASSERT_TRUE(temporary.ends_with(".json.tmp." + std::to_string(::getpid()))) << temporary;
  const std::string other = (kept / "summary.json").string();
  touch(temporary);
  touch(other);
  {
    const QuitRemovesFile registered(temporary), not_temporary(other);
    quit_removes_folders({outer, inner});
    remove_on_quit();
  }
  EXPECT_FALSE(fs::exists(temporary));
  EXPECT_TRUE(fs::exists(other)) << "a name not ending in .tmp.<pid> is never removed";
  EXPECT_FALSE(fs::exists(outer)) << "the made folders, empty, innermost first";
  // A made folder that holds a result stays, and so does the one around it.
  fs::create_directories(inner);
  touch(inner / "particles.csv");
  quit_removes_folders({outer, inner});
  remove_on_quit();
  EXPECT_TRUE(fs::exists(inner / "particles.csv"));
  // Unregistered (the file's writer is done, the command has ended): nothing is removed.
  quit_removes_folders({});
  fs::remove(inner / "particles.csv");
  touch(temporary);
  remove_on_quit();
  EXPECT_TRUE(fs::exists(inner));
  EXPECT_TRUE(fs::exists(temporary));
}

// converge's temperature errors: a particle vaporised in either run keeps the temperature it left
// with, which is no field value, so it is left out (what vaporised is v_v's error).
TEST(RunReport, TemperatureErrorsCompareParticlesLiveInBothRuns) {
  RunResult reference, rung;
  reference.temperature = {400, 500, 700, 320};
  reference.alive = {1, 1, 0, 1};  // particle 2 vaporised at 700 K
  rung.temperature = {403, 496, 350, 320};
  rung.alive = {1, 1, 1, 0};  // particle 2 did not; particle 3 did
  const TemperatureError e = temperature_error(rung, reference);
  EXPECT_EQ(e.compared, 2u);
  EXPECT_DOUBLE_EQ(e.max.value(), 4.0);
  EXPECT_DOUBLE_EQ(e.l2.value(), std::sqrt((9.0 + 16.0) / 2.0));
  // No particle live in both: no error, not one of 0 K.
  reference.alive = rung.alive = {0, 0, 0, 0};
  const TemperatureError none = temperature_error(rung, reference);
  EXPECT_EQ(none.compared, 0u);
  EXPECT_FALSE(none.l2);
  EXPECT_FALSE(none.max);
}

// A sweep's or converge's stage table sums its runs' seconds and calls and says, for a stage
// some runs skipped, in which of them and why (the runs' labels grouped by reason, a few named).
TEST(RunReport, AStageTableOfSeveralRunsSaysWhichSkippedAStageAndWhy) {
  const auto run = [](const std::string& label, StageTime phases, StageTime rebuild) {
    StageTable stages = {{"setup", {0.25, 1, ""}}, {"phases", phases}, {"rebuild", rebuild}};
    return LabelledRun{label, stages, Counts{}};
  };
  const StageTime cold{0, 0, "no particle at the melting temperature"};
  const StageTime rigid{0, 0, "no contact graph"}, empty{0, 0, "no particles"};
  std::vector<LabelledRun> runs = {run("P = 1", cold, rigid), run("P = 2", {0.5, 3, ""}, rigid),
                                   run("P = 3", {1.0, 4, ""}, rigid)};
  std::vector<std::string> lines = stage_total_lines(runs, {0.125, 1, ""});
  ASSERT_EQ(lines.size(), 5u);
  EXPECT_EQ(lines[0], "stages over 3 runs, s");
  EXPECT_CONTAINS(lines[1], "0.7500  (3 calls)");
  EXPECT_CONTAINS(lines[2],
                  "1.5000  (7 calls); skipped in 1 of 3 runs: no particle at the "
                  "melting temperature (P = 1)");
  EXPECT_CONTAINS(lines[3], "-  skipped: no contact graph");  // every run, one reason: no names
  EXPECT_NOT_CONTAINS(lines[3], "P = ");
  EXPECT_CONTAINS(lines[4], "output");
  EXPECT_CONTAINS(lines[4], "0.1250  (1 call)");
  // Every run skipped it, for two reasons: each names its runs, three at most.
  for (int k = 4; k <= 8; ++k) runs.push_back(run("P = " + std::to_string(k), cold, empty));
  lines = stage_total_lines(runs, {0.125, 1, ""});
  EXPECT_CONTAINS(lines[3],
                  "skipped: no contact graph (P = 1, P = 2, P = 3); no particles "
                  "(P = 4, P = 5, P = 6 and 2 more)");
  EXPECT_CONTAINS(lines[2],
                  "skipped in 6 of 8 runs: no particle at the melting temperature "
                  "(P = 1, P = 4, P = 5 and 3 more)");
  EXPECT_TRUE(stage_total_lines({}, {0.125, 1, ""}).empty());  // no run ended: no table
}

TEST(RunReport, AClosedLedgerGivesNoWarning) {
  EXPECT_TRUE(open_ledger_warnings(SimulationSpec{}, closed_ledger()).empty());
  EnergyLedger round_off = closed_ledger();
  round_off.escaped += 1e-15, round_off.stored += 1e-12;  // round-off and a 1e-10 solver's error
  EXPECT_TRUE(open_ledger_warnings(SimulationSpec{}, round_off).empty());
}

TEST(RunReport, AnOpenLedgerIsNamedWithItsSize) {
  EnergyLedger optics = closed_ledger();
  optics.escaped -= 1e-6;
  const auto o = open_ledger_warnings(SimulationSpec{}, optics);
  ASSERT_EQ(o.size(), 1u);
  EXPECT_CONTAINS(o[0], "optics ledger is open by 1e-06");
  EnergyLedger heat = closed_ledger();
  heat.stored = 0.0;  // the stiff-wall case before the fix: the absorbed heat in no bin
  const auto h = open_ledger_warnings(SimulationSpec{}, heat);
  ASSERT_EQ(h.size(), 1u);
  EXPECT_CONTAINS(h[0], "heat ledger is open by 0.833");
  // A loose solver tolerance widens what counts as closed: 1e-3 of the absorbed at 1e-4.
  SimulationSpec loose;
  loose.thermal.tolerance = 1e-4;
  EnergyLedger slightly = closed_ledger();
  slightly.stored += 6e-4;
  EXPECT_TRUE(open_ledger_warnings(loose, slightly).empty());
  EXPECT_EQ(open_ledger_warnings(SimulationSpec{}, slightly).size(), 1u);
  EnergyLedger nan = closed_ledger();
  nan.walls = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(open_ledger_warnings(SimulationSpec{}, nan).size(), 1u);
  // Walls that heat: the beam's 3e-43 J is no scale for 3.7e-7 J moved from the walls into the
  // particles (a stiff wall's 2.5e-8 J of round-off read as open by 2.9e34); the gross flow is.
  EnergyLedger walled;
  walled.absorbed = 3e-43, walled.stored = 3.665191e-7, walled.walls = -3.665191e-7 + 3e-43;
  EXPECT_TRUE(open_ledger_warnings(SimulationSpec{}, walled).empty());
  walled.walls = -3.410605e-7;
  const auto w = open_ledger_warnings(SimulationSpec{}, walled);
  ASSERT_EQ(w.size(), 1u);
  EXPECT_CONTAINS(w[0], "heat ledger is open by 0.0695 of the energy it moves");
}

using beampack::testing::svg_texts;

// convergence.svg: log axes label whole decades once each; an error of 0 is drawn in a band of
// its own below the axis, labelled 0 (it used to be drawn at 1e-6 as if measured, then as a
// hollow circle on the lower edge, beside the lowest tick's label; and labels repeated).
// A scene beyond the machine's memory is refused before set-up, naming the key that needs the
// most: it ended in std::bad_alloc (exit 1) after minutes of allocation.
// Temperatures risen so far that the solves' accuracy in kelvin nears the melting-to-vapour gap
// (beam.power = 1e20 W: a particle beside the hottest ended 2 K below its initial temperature,
// and the solvers disagreed on v_v) are said; a run of ordinary temperatures says nothing.
TEST(RunReport, TemperaturesBeyondTheSolvesResolutionOfThePhasesAreSaid) {
  SimulationSpec spec;  // tolerance 1e-10, theta_m 600 K, theta_v 700 K, from 300 K
  spec.materials.front().conductivity = 100;
  Counts counts;
  counts.iterative_heat_steps = 1;
  const auto phase_resolution_warning = [&](const SimulationSpec& s, const Figures& figures) {
    return beampack::phase_resolution_warning(s, figures, counts);
  };
  Figures f;
  f.max_temperature = 4e2 + 300;
  EXPECT_FALSE(phase_resolution_warning(spec, f));
  f.max_temperature = 4e17 + 300;
  const auto said = phase_resolution_warning(spec, f);
  ASSERT_TRUE(said);
  EXPECT_CONTAINS(*said, "misplace a particle beside the hottest by ~4e+07 K, against 100 K");
  f.max_temperature = 4e10 + 300;  // 4 K against 100 K: the phases are resolved
  EXPECT_FALSE(phase_resolution_warning(spec, f));
  spec.thermal.tolerance = 1e-8;  // 400 K
  EXPECT_TRUE(phase_resolution_warning(spec, f));
  // No iterative solve to blame: the direct solver's round-off (4e-5 K), also where "auto" picked
  // it in every step (it warned as if it had iterated), no conduction at all, or explicit steps.
  counts.iterative_heat_steps = 0;
  EXPECT_FALSE(phase_resolution_warning(spec, f));
  counts.iterative_heat_steps = 1;
  spec.materials.front().conductivity = 0;
  EXPECT_FALSE(phase_resolution_warning(spec, f));
  spec.materials.front().conductivity = 100;
  spec.thermal.phi = 0;
  EXPECT_FALSE(phase_resolution_warning(spec, f));
}

// Particles colder than the run's floor (the least of the starting and wall temperatures) are
// an iterative solve's error (fixed-point at thermal.tolerance = 0.1 left one at 296.98 K in a
// run that only heats, with no word but the generic resolution warning), or a defect where none
// ran; round-off below it is not.
TEST(RunReport, AParticleBelowTheRunsFloorIsSaid) {
  const SimulationSpec spec;
  Counts counts;
  counts.iterative_heat_steps = 3;
  Particles p;
  p.radius = {1e-5, 1e-5, 1e-5};
  p.temperature = {300.0, 299.99999999999966, 650.0};  // the direct solver's worst at K = 1e6
                                                       // when it measured from 0 K
  EXPECT_FALSE(below_floor_warning(spec, 300, p, counts));
  p.temperature = {299.9, 296.975, 650.0};
  const auto said = below_floor_warning(spec, 300, p, counts);
  ASSERT_TRUE(said);
  EXPECT_CONTAINS(*said, "2 particles ended below 300 K");
  EXPECT_CONTAINS(*said, "(particle 1: 3.02 K below it): the heat solves' error did it");
  EXPECT_FALSE(below_floor_warning(spec, 250, p, counts));  // walls at 250 K may cool them so far
  counts.iterative_heat_steps = 0;  // the factorisation's round-off cannot do it
  EXPECT_CONTAINS(*below_floor_warning(spec, 300, p, counts), "please report this run file");
}

// A caller's particles start at their own temperatures, which set the floor: a bed half at 250 K
// under the beam warned that a solve had taken 206 particles below 300 K (diff review).
TEST(RunReport, TheFloorIsTheParticlesOwnStartingTemperatures) {
  SimulationSpec spec = beampack::testing::quick_scene();
  spec.thermal.walls = {Wall{0, 0.0, 0.0, 400.0, -1}};  // a wall warmer than the bed
  Particles p = make_packing(spec.packing);
  for (std::size_t i = 0; i < p.size(); i += 2) p.temperature[i] = 250;
  Simulation sim(spec, p);
  EXPECT_EQ(sim.temperature_floor(), 250.0);
  sim.run();
  for (const std::string& w : sim.run_warnings()) EXPECT_NOT_CONTAINS(w, "ended below") << w;
}

TEST(RunReport, ASceneBeyondTheMachinesMemoryIsRefusedByName) {
  constexpr double k24GiB = 24.0 * (1 << 30);
  SimulationSpec paper;  // 1000 rays on 1000 particles
  paper.beam.rays = 1000, paper.packing.count = 1000;
  EXPECT_NO_THROW(refuse_beyond_memory(paper, k24GiB));
  EXPECT_LT(least_memory_need(paper), 1e7);
  SimulationSpec rays = paper;
  rays.beam.rays = 100'000'000;  // 44 GB measured by extrapolation: 437 bytes per ray
  EXPECT_GE(least_memory_need(rays), 4e10);
  testing::expect_error<InputError>([&] { refuse_beyond_memory(rays, k24GiB); },
                                    "`beam.rays` = 100000000:", "at least 40 GB",
                                    "more than the 25.8 GB of this machine; lower `beam.rays`");
  SimulationSpec particles = paper;
  particles.packing.count = 100'000'000;
  testing::expect_error<InputError>(
      [&] { refuse_beyond_memory(particles, k24GiB); },
      "`packing.count` = 100000000: the run needs at least 40 GB with `beam.rays` = 1000 (",
      "; lower `packing.count`");
  // Without pulses no ray is drawn and no ray scene made: 100 bytes a particle (102 measured), so
  // 10^8 particles fit, 3 10^8 do not, and rays cost nothing, however many.
  SimulationSpec untraced = particles;
  untraced.pulses.count = 0;
  EXPECT_NO_THROW(refuse_beyond_memory(untraced, k24GiB));
  EXPECT_GE(least_memory_need(untraced), 1e10);
  untraced.beam.rays = 1'000'000'000;
  EXPECT_NO_THROW(refuse_beyond_memory(untraced, k24GiB));
  untraced.packing.count = 300'000'000;
  testing::expect_error<InputError>(
      [&] { refuse_beyond_memory(untraced, k24GiB); },
      "at least 30 GB without pulses (no rays drawn) (100 bytes per particle)");
  particles.packing.source = "file";  // counted when the file is read: only the rays are known
  EXPECT_NO_THROW(refuse_beyond_memory(particles, k24GiB));
  particles.packing.file = "bed.xyz";
  // Once it is read: its particles count.
  testing::expect_error<InputError>([&] { refuse_beyond_memory(particles, k24GiB, 100'000'000); },
                                    "`packing.file` = \"bed.xyz\" (100000000 particles): the run "
                                    "needs at least 40 GB with `beam.rays` = 1000",
                                    "; lower the particle count");
  // The contacts conduction needs: 100 bytes more per particle with a conductivity (141 measured),
  // 50 with walls alone (58 measured). 6 10^7 particles need 24 GB without them: they fit.
  SimulationSpec conducting = paper;
  conducting.packing.count = 60'000'000;
  EXPECT_NO_THROW(refuse_beyond_memory(conducting, k24GiB));
  conducting.thermal.walls = {Wall{}};
  EXPECT_GE(least_memory_need(conducting), 2.7e10);
  conducting.thermal.walls.clear();
  conducting.materials.front().conductivity = 100;
  testing::expect_error<InputError>([&] { refuse_beyond_memory(conducting, k24GiB); },
                                    "at least 30 GB with `beam.rays` = 1000 (400 bytes per ray, "
                                    "500 bytes per particle with its contacts)");
  rays.packing.source = "file";
  testing::expect_error<InputError>([&] { refuse_beyond_memory(rays, k24GiB); },
                                    "`beam.rays` = 100000000: the run needs at least 40 GB for its "
                                    "rays alone (400 bytes per ray");
  EXPECT_GT(machine_memory(), 1e8);
}

// MODEL.md section 2: tau = xi R / c ("auto"), or E / P ("energy"); thermal.dt = "paper" is the
// paper's ray time step xi R / c. R = L (D^3 / N)^(1/3) = 0.325 (1e-9 / 1000)^(1/3) = 3.25e-5 m.
TEST(RunReport, PulseDurationAndThePapersStepFollowTheirFormulas) {
  constexpr double kC = 299'792'458.0, kR = 3.25e-5;
  RunSources auto_tau;
  auto_tau.preset = "zohdi2013";
  auto_tau.sets = {"pulses.duration=\"auto\"", "pulses.xi=0.08", "thermal.dt=\"paper\""};
  const RunConfig a = load_run_config(auto_tau);
  EXPECT_NEAR(a.sim.pulses.duration, 0.08 * kR / kC, 1e-12 * a.sim.pulses.duration);
  EXPECT_NEAR(a.sim.dt, 0.08 * kR / kC, 1e-12 * a.sim.dt);
  EXPECT_EQ(a.packing, nullptr);  // generated, not read: nothing to hand on
  RunSources energy;
  energy.preset = "zohdi2013";
  energy.sets = {"pulses.duration=\"energy\"", "pulses.energy=3e-9", "beam.power=1500"};
  const RunConfig e = load_run_config(energy);
  EXPECT_DOUBLE_EQ(e.sim.pulses.duration, 3e-9 / 1500);
  EXPECT_DOUBLE_EQ(e.sim.dt, 0.0);  // the preset's "pulse": one step per pulse flight
  // A file's spheres differ in size: R is their median (the paper, remark after (3.11)), 3e-5 m
  // here, and for an even count the mean of the middle two. Was sample.size / 100 = 1e-5 m.
  const std::filesystem::path dir = beampack::testing::fresh_dir("paper_step");
  for (const auto& [rows, median] :
       {std::pair{"1 1 1 1e-5\n2 2 2 2e-4\n3 3 3 3e-5\n", 3e-5},
        std::pair{"1 1 1 1e-5\n2 2 2 2e-4\n3 3 3 3e-5\n4 4 4 4e-5\n", 3.5e-5}}) {
    std::ofstream(dir / "bed.xyz") << "x y z r\n" << rows;
    RunSources file = auto_tau;
    file.sets.push_back("packing.source=\"file\"");
    file.sets.push_back("packing.file=\"" + (dir / "bed.xyz").string() + "\"");
    file.sets.push_back("sample.size=5");
    const RunConfig f = load_run_config(file);
    EXPECT_NEAR(f.sim.pulses.duration, 0.08 * median / kC, 1e-12 * f.sim.pulses.duration) << rows;
    EXPECT_NEAR(f.sim.dt, 0.08 * median / kC, 1e-12 * f.sim.dt) << rows;
    EXPECT_NEAR(paper_step(f.sim.packing, f.xi), 0.08 * median / kC, 1e-12 * f.sim.dt)
        << rows;                    // converge's
    ASSERT_NE(f.packing, nullptr);  // read once, for the simulation too
    EXPECT_EQ(f.packing->size(), std::count(rows, rows + std::strlen(rows), '\n'));
  }
  // A resumed run's particles come from its checkpoint, not the file (which is gone): made for
  // the resolved spec (its start temperature, its materials; Simulation::saved_packing checks
  // them), and their median radius gives tau.
  RunSources resumed = auto_tau;
  resumed.sets.push_back("packing.source=\"file\"");
  resumed.sets.push_back("packing.file=\"" + (dir / "gone.xyz").string() + "\"");
  resumed.sets.push_back("sample.size=5");
  int made = 0;
  resumed.saved_packing = [&](const SimulationSpec& spec) {
    ++made;
    EXPECT_EQ(spec.materials.size(), 1u);
    Particles saved;
    saved.add(Vec3(1, 1, 1), 2e-5, 0, spec.packing.initial_temperature);
    saved.add(Vec3(2, 2, 2), 3e-5, 0, spec.packing.initial_temperature);
    return saved;
  };
  const RunConfig r = load_run_config(resumed);
  EXPECT_EQ(made, 1);
  ASSERT_NE(r.packing, nullptr);
  EXPECT_EQ(r.packing->temperature, std::vector<double>(2, 300.0));
  EXPECT_NEAR(r.sim.pulses.duration, 0.08 * 2.5e-5 / kC,
              1e-12 * r.sim.pulses.duration);             // their median
  EXPECT_EQ(load_run_config(auto_tau).packing, nullptr);  // a generated packing takes none
  RunSources generated = auto_tau;
  generated.saved_packing = resumed.saved_packing;
  EXPECT_EQ(load_run_config(generated).packing, nullptr);
  EXPECT_EQ(made, 1);  // and is not asked for one
  // The file is read once every key is: a misspelt key is named first, not a missing file.
  RunSources typo = auto_tau;
  typo.sets.push_back("packing.source=\"file\"");
  typo.sets.push_back("packing.file=\"" + (dir / "no such bed.xyz").string() + "\"");
  typo.sets.push_back("beam.rayz=5");
  testing::expect_error<InputError>([&] { load_run_config(typo); }, "unknown key `beam.rayz`");
}

TEST(RunReport, LogChartsLabelEachDecadeOnceAndShowZerosAsZeros) {
  const Chart chart{"t", "x", "y", true, true, {{"a", {0.5, 2.0, 12.0}, {3e-5, 0.2, 0.0}}}};
  const std::string svg = render_svg(chart);
  EXPECT_EQ(svg_texts(svg, "y=\"380\""), (std::vector<std::string>{"1e-1", "1e0", "1e1", "1e2"}))
      << svg;
  // The 0 is labelled once, beside its own band below the axis (tests/test_charts.cpp).
  EXPECT_EQ(svg_texts(svg, "x=\"8\""),
            (std::vector<std::string>{"1e-5", "1e-4", "1e-3", "1e-2", "1e-1", "1e0", "0"}))
      << svg;
}

// Values a few ulps apart on a negative axis: the ticks still end (a step below the values' last
// digit once stalled the loop until memory ran out).
TEST(RunReport, NearlyEqualNegativeValuesStillGiveAFewTicks) {
  const double a = -1e6, b = std::nextafter(a, 0.0);
  const Chart chart{"t", "x", "y", false, false, {{"s", {a, b}, {1.0, 2.0}}}};
  EXPECT_LT(svg_texts(render_svg(chart), "y=\"380\"").size(), 25u);
}

// sweep.svg: a swept word (`beam.profile`) is named on the x axis; a single value gets a span
// around it rather than [v, v + 1].
TEST(RunReport, SweepChartsNameWordValuesAndSpanASingleValue) {
  Chart words{"t",
              "beam.profile",
              "v_v",
              false,
              false,
              {{"a", {0, 1, 2}, {0.03, 0.02, 0.03}}},
              {"flat", "gaussian", "exponential"}};
  EXPECT_EQ(svg_texts(render_svg(words), "y=\"380\""),
            (std::vector<std::string>{"flat", "gaussian", "exponential"}));
  const Chart one{"t", "x", "y", false, false, {{"a", {1, 2}, {0.03, 0.03}}}};
  const std::string svg = render_svg(one);
  EXPECT_EQ(svg_texts(svg, "x=\"8\"").back(), "0.04") << svg;  // not 1: the axis spans 0 to 0.047
}

}  // namespace
}  // namespace beampack::tools
