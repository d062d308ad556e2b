#include "tools/run_config.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <limits>
#include <numbers>
#include <set>
#include <sstream>

#include <unistd.h>

#include "engine/fresnel.h"
#include "geometry/error.h"

namespace beampack::tools {
namespace {

constexpr double kBig = std::numeric_limits<double>::max();

// The caps are the library's (thermal/material.h, thermal/thermal_model.h, engine/beam.h,
// engine/simulation.h), with the measurements behind them; the run file's messages state them.

// packing.radius: the limit of every particle's radius (geometry/packing.h); from 1e3 m the heat
// ledger opens already (a warning says so).
constexpr Cap kFileRadius{kMaxParticleRadius, kMaxParticleRadiusWhy};

// `value` of `key`, refused above the cap with its reason (Params::number states a range only).
// The value is shown in full: 1.0000001e+20 is not "1e+20" above a limit of 1e+20.
double capped(const Params& p, const std::string& key, double value, const Cap& cap) {
  if (!(value > cap.limit)) return value;
  std::array<char, 32> shown;
  const auto end = std::to_chars(shown.data(), shown.data() + shown.size(), value).ptr;
  p.fail(key, std::string(shown.data(), end), cap_limit(cap));
}

double number_up_to(Params& p, const std::string& key, double fallback, double lo, const Cap& cap,
                    bool lo_open = false) {
  return capped(p, key, p.number(key, fallback, lo, kBig, lo_open, false, cap.limit), cap);
}

// Every key is read whatever the source, so `beampack config` lists them all and a preset's
// keys never count as unused; the ones a source ignores are documented as such.
void read_packing(Params& p, PackingSpec& s) {
  // Embree's boxes are floats: far below 1e-12 m their corners underflow and every ray escapes.
  s.sample_size = p.number("sample.size", 1e-3, 1e-12, 1e6);
  s.source =
      p.choice("packing.source", "random-overlap", {"random-overlap", "rsa", "lattice", "file"});
  s.count = std::size_t(p.integer("packing.count", 1000, 0, 100'000'000));
  if (const std::string problem = lattice_count_problem(s.count);
      s.source == "lattice" && !problem.empty())  // known before any run of a sweep starts
    p.fail("packing.count", std::to_string(s.count), problem);
  s.radius_ratio = p.number("packing.radius_ratio", 0.325, 0, 10, true);
  s.solid_fraction = p.number("packing.solid_fraction", 0.3, 0, 0.5, true, true);
  s.seed = std::uint64_t(p.integer("packing.seed", 1, 0, std::numeric_limits<std::int64_t>::max()));
  // A later layer that switches to another source (`--set packing.source=rsa` over a run file
  // with a file) drops the file keys; within one layer they contradict and are refused below.
  if (s.source != "file")
    for (const char* key : {"packing.file", "packing.radius"})
      if (p.set_later("packing.source", key)) p.forget(key);
  s.file = p.path("packing.file");
  s.file_radius = number_up_to(p, "packing.radius", 0.0, 0, kFileRadius);
  if (s.source != "file" && !s.file.empty())  // it would be read by nobody
    p.fail("packing.file", "\"" + s.file + "\"",
           "needs packing.source = \"file\" (it is \"" + s.source + "\")");
  if (s.source != "file" && s.file_radius != 0.0)
    p.fail("packing.radius", shown_number(s.file_radius),
           "applies to packing.source = \"file\" only");
  if (s.source == "file" && s.file.empty())
    p.fail("packing.file", "\"\"", "required with packing.source = \"file\"");
}

void read_beam(Params& p, BeamSpec& b) {
  b.power = number_up_to(p, "beam.power", 6000, 0, kPowerCap, true);
  b.diameter_fraction = p.number("beam.diameter_fraction", 0.3, 0, 10, true);
  b.rays = std::size_t(p.integer("beam.rays", 1000, 1, 100'000'000));
  b.sampling = p.choice("beam.sampling", "random", {"random", "stratified"});
  b.profile = p.choice("beam.profile", "exponential", {"exponential", "flat", "gaussian"});
  b.decay = p.number("beam.decay", 2.0, 0, 1e3);
  b.gaussian_width = p.number("beam.gaussian_width", 1.0, 0, 1e3, true);
  b.seed = std::uint64_t(p.integer("beam.seed", 1, 0, std::numeric_limits<std::int64_t>::max()));
  // Stratified rays are fixed: a resample there is a key the scene does not read
  // (check_unread_keys: refused on the command line, a warning in a run file).
  b.resample = p.flag("beam.resample", false) && b.sampling == "random";
  const double dx = p.number("beam.direction_x", 1.0, -1, 1);
  const double dy = p.number("beam.direction_y", 0.0, -1, 1);
  const double dz = p.number("beam.direction_z", 0.0, -1, 1);
  const Vec3 d(dx, dy, dz);
  if (d.norm() < 1e-12) {
    std::ostringstream v;
    v << dx << " (with beam.direction_y = " << dy << ", beam.direction_z = " << dz << ")";
    p.fail("beam.direction_x", v.str(), "the direction must not be zero (length >= 1e-12)");
  }
  b.direction = d.normalized();
}

// Whether `key` was given after `other`: in a later layer, or given where `other` is a default.
bool given_after(const Params& p, const std::string& key, const std::string& other) {
  return p.set_later(key, other) || (p.has(key) && !p.has(other)) ||
         (p.set_on_command_line(key) && !p.set_on_command_line(other));
}

// Two keys that must keep an order, low < high: the refusal names the key the user set last
// (a later layer, --set over a file or preset, anything over a default) and where the other one
// came from, so that `--set material.melt_temperature=800` over a preset blames that --set, not
// the preset's vapour temperature.
void check_order(const Params& p, const std::string& low_key, double low,
                 const std::string& high_key, double high, const std::string& why = "") {
  if (low < high) return;
  if (given_after(p, low_key, high_key))
    p.fail(low_key, shown_number(low),
           "must be < " + high_key + " = " + shown_number(high) + " (" + p.source_of(high_key) +
               ")" + why);
  p.fail(
      high_key, shown_number(high),
      "must be > " + low_key + " = " + shown_number(low) + " (" + p.source_of(low_key) + ")" + why);
}

// A linearly polarised beam stays linear only on real indices >= 1 (tracer.cpp); the message
// blames whichever of the polarisation and the offending index was given last, with the other's
// source, as check_order does.
void check_linear_light(const Params& p, const MaterialOptics& m) {
  const std::pair<const char*, bool> offending[] = {{"optics.n_solid", m.n_solid.real() < 1.0},
                                                    {"optics.k_solid", m.n_solid.imag() > 0.0},
                                                    {"optics.n_liquid", m.n_liquid.real() < 1.0},
                                                    {"optics.k_liquid", m.n_liquid.imag() > 0.0}};
  const std::string why =
      ": the reflected light is elliptical there (a metal, k > 0, or an index below 1), which is "
      "not followed; use optics.polarisation = \"unpolarised\"";
  const std::string polarisation = "optics.polarisation";
  for (const auto& [key, bad] : offending) {
    if (!bad) continue;
    if (given_after(p, key, polarisation))
      p.fail(key, p.shown(key),
             "with " + polarisation + " = " + p.shown(polarisation) + " (" +
                 p.source_of(polarisation) + ")" + why);
    p.fail(polarisation, p.shown(polarisation),
           "with " + std::string(key) + " = " + p.shown(key) + " (" + p.source_of(key) + ")" + why);
  }
}

void read_optics(Params& p, OpticsSpec& o) {
  MaterialOptics m;  // the optics' own limits (engine/fresnel.h)
  m.n_solid = {p.number("optics.n_solid", 1.4, 0, kMaxIndex, true),
               p.number("optics.k_solid", 0.0, 0, kMaxIndex)};
  m.n_liquid = {p.number("optics.n_liquid", 1.0, 0, kMaxIndex, true),
                p.number("optics.k_liquid", 0.0, 0, kMaxIndex)};
  m.mu_hat = p.number("optics.mu_hat", 1.0, kMinMu, kMaxMu);
  o.materials = {m};
  o.cutoff = p.number("optics.cutoff", 1e-10, 0, 1, false, true);  // 1 would end every ray unused
  o.max_bounces = int(p.integer("optics.max_bounces", 1000, 1, 1'000'000));
  double degrees = 0.0;
  const std::string word = p.number_or_word("optics.polarisation", degrees, 0, 180, {"unpolarised"},
                                            "unpolarised", "degrees", false);
  o.polarisation = {word.empty(), degrees * std::numbers::pi / 180.0};
  o.packets = p.flag("optics.packets", true);
  if (o.polarisation.linear) check_linear_light(p, m);
}

void read_material(Params& p, Material& m) {
  m.density = number_up_to(p, "material.density", 1000, 0, kDensityCap, true);
  m.c_solid = number_up_to(p, "material.c_solid", 1000, 0, kHeatCapacityCap, true);
  m.c_liquid = number_up_to(p, "material.c_liquid", 2000, 0, kHeatCapacityCap, true);
  m.conductivity = number_up_to(p, "material.conductivity", 0, 0, kConductivityCap);
  m.melt_temperature = number_up_to(p, "material.melt_temperature", 600, 0, kTemperatureCap, true);
  m.vapor_temperature =
      number_up_to(p, "material.vapor_temperature", 700, 0, kTemperatureCap, true);
  m.latent_melt = number_up_to(p, "material.latent_melt", 1000, 0, kLatentBandCap);
  m.latent_solidify = number_up_to(p, "material.latent_solidify", 1000, 0, kLatentBandCap);
  m.latent_vapor = number_up_to(p, "material.latent_vapor", 1000, 0, kLatentBandCap);
  check_order(p, "material.melt_temperature", m.melt_temperature, "material.vapor_temperature",
              m.vapor_temperature);
  m.validate("material");
}

// thermal.walls: isothermal walls on faces of the sample cube [0, D]^3, e.g. "z-" or "x-,x+";
// a particle within thermal.wall_reach of a face (surface to face) exchanges heat with it.
std::vector<Wall> read_walls(Params& p, double size) {
  const std::string faces = p.text("thermal.walls", "");
  const double temperature =
      number_up_to(p, "thermal.wall_temperature", 300, 0, kTemperatureCap, true);
  const double reach = p.number("thermal.wall_reach", 0, 0, kBig);
  const double conductance =
      capped(p, "thermal.wall_conductance",
             p.number_or("thermal.wall_conductance", -1, 0, kWallConductanceCap.limit, -1,
                         "pi K R, from material.conductivity"),
             kWallConductanceCap);
  std::vector<Wall> walls;
  std::vector<std::string> seen;
  std::stringstream list(faces);
  for (std::string face; std::getline(list, face, ',');) {
    face.erase(std::remove(face.begin(), face.end(), ' '), face.end());
    const std::string axes = "xyz";
    if (face.size() != 2 || axes.find(face[0]) == std::string::npos ||
        (face[1] != '-' && face[1] != '+'))
      p.fail("thermal.walls", "\"" + faces + "\"",
             "faces are x-, x+, y-, y+, z-, z+ separated by commas");
    if (std::count(seen.begin(), seen.end(), face))  // a face listed twice would conduct twice
      p.fail("thermal.walls", "\"" + faces + "\"", "face " + face + " is listed twice");
    seen.push_back(face);
    walls.push_back({int(axes.find(face[0])), face[1] == '-' ? 0.0 : size, reach, temperature,
                     conductance < 0 ? -1.0 : conductance});
  }
  return walls;
}

// Where a run uses the paper's ray time step xi R / c, derived once every key is read (for a
// file packing R comes from the file: a misspelt key is named before the file is read).
struct PaperStepUse {
  double xi = 0.05;
  bool duration = false;  // pulses.duration = "auto"
  bool dt = false;        // thermal.dt = "paper"
};

// thermal.dt: seconds, "pulse" (one step per pulse flight: the event-driven limit) or "paper"
// (xi R / c, the paper's ray time step: derive_paper_step).
void read_thermal(Params& p, SimulationSpec& s, PaperStepUse& use) {
  ThermalSpec& t = s.thermal;
  t.time_scaling = number_up_to(p, "thermal.time_scaling", 1e6, 0, kTimeScalingCap, true);
  t.phi = p.number("thermal.phi", 1.0, 0, 1);
  t.solver = p.choice("thermal.solver", "auto", {"fixed-point", "cg", "direct", "auto"});
  t.tolerance = p.number("thermal.tolerance", 1e-10, 0, 0.1, true);
  t.max_iterations = int(p.integer("thermal.max_iterations", 1000, 1, 100'000'000));
  t.max_substeps = int(p.integer("thermal.max_substeps", 1000, 1, 100'000'000));
  s.max_staggers = int(p.integer("thermal.max_staggers", 4, 0, 1000));
  double dt = 0;
  const std::string word = p.number_or_word("thermal.dt", dt, 0, kBig, {"pulse", "paper"}, "pulse",
                                            "seconds", true, kStepCap.limit);
  capped(p, "thermal.dt", dt, kStepCap);
  use.dt = word == "paper";
  s.dt = word == "pulse" || use.dt ? 0.0 : dt;
  t.validate();
}

// kMaxStepsPerCrossing (engine/simulation.h), checked here to name the run file's line.
void check_steps_per_crossing(Params& p, const SimulationSpec& s, bool paper) {
  if (steps_per_crossing(s) > kMaxStepsPerCrossing)
    p.fail("thermal.dt",
           paper ? "\"paper\" (xi R / c = " + shown_number(s.dt) + " s)" : shown_number(s.dt),
           least_step_limit(s));
}

// tau: seconds, or "auto" = xi R / c (the paper's ray time step: derive_paper_step), or from
// pulses.energy.
void read_pulses(Params& p, SimulationSpec& s, PaperStepUse& use) {
  s.pulses.count = int(p.integer("pulses.count", 20, 0, 10'000'000));
  double tau = 0;
  const std::string word = p.number_or_word("pulses.duration", tau, 0, kBig, {"auto", "energy"},
                                            "auto", "seconds", true, kDurationCap.limit);
  capped(p, "pulses.duration", tau, kDurationCap);
  use.xi = p.number("pulses.xi", 0.05, 0, 10, true);
  use.duration = word == "auto";
  const double energy = p.number("pulses.energy", 1e-9, 0, kBig, true);
  if (word == "energy") tau = energy / s.beam.power;
  // Each input is in range, but a quotient can still overflow or underflow (found by fuzz/).
  if (word == "energy" && !(std::isfinite(tau) && tau > 0 && tau <= kDurationCap.limit)) {
    std::ostringstream m;
    m << "`pulses.duration` = \"energy\" gives tau = " << tau
      << " s (pulses.energy / beam.power): must be > 0 "
      << "and <= " << kDurationCap.limit << " " << kDurationCap.why
      << "; give pulses.duration in seconds";
    throw InputError(m.str());
  }
  s.pulses.duration = tau;
  double period = 0;
  const std::string pw = p.number_or_word("pulses.period", period, 0, kBig, {"auto"}, "auto",
                                          "seconds", true, kStepCap.limit);
  capped(p, "pulses.period", period, kStepCap);
  s.pulses.period = pw == "auto" ? 0.0 : period;
}

// xi R / c where the run uses it, R the packing's radius; a file's particles are read here, once
// (the simulation takes them).
void derive_paper_step(RunConfig& c, const PaperStepUse& use) {
  c.xi = use.xi;
  if (!use.duration && !use.dt) return;
  if (c.sim.packing.source == "file" && !c.packing)
    c.packing = std::make_shared<const Particles>(make_packing(c.sim.packing));
  const double step = paper_step(c.sim.packing, use.xi, c.packing.get());
  if (std::isfinite(step) && step > 0 && step <= kStepCap.limit) {
    if (use.duration) c.sim.pulses.duration = step;
    if (use.dt) c.sim.dt = step;
    return;
  }
  std::ostringstream m;
  m << (use.duration ? "`pulses.duration` = \"auto\" gives tau" : "`thermal.dt` = \"paper\" gives")
    << " = pulses.xi * R / c = " << step
    << " s (R from sample.size and packing.*, or a file's median radius): must be > 0 and <= "
    << kStepCap.limit << " s; give " << (use.duration ? "pulses.duration" : "thermal.dt")
    << " in seconds";
  throw InputError(m.str());
}

// A key that some scenes do not read: whether this one does, the key that decides it, and what
// would make the key apply.
struct KeyUse {
  const char* key;
  bool applies;
  const char* decider;
  std::string needs;
};

// Keys the scene does not read. One set in this run (--set, a swept value) would give the
// numbers of a run without it, without a word: refused. A preset or a run file may hold it
// (`beampack config` prints every key; a user may switch a preset's profile away from its
// beam.decay), and so may a sweep over the deciding key (beam.profile), whose other runs use it.
// A run file's value other than the key's default was likely meant for this scene: a warning
// (returned, for the command to print once) rather than a refusal.
// pulses.xi is among them unless `xi_always_read` (converge's time-step ladder uses it whatever the
// pulse duration); a sweep over thermal.dt, its other decider, may hold it too.
std::vector<std::string> check_unread_keys(const Params& p, const SimulationSpec& s,
                                           const PaperStepUse& paper, bool xi_always_read,
                                           std::vector<UnreadKey>& unread) {
  const std::string& source = s.packing.source;
  const std::string is_source = " (it is " + p.shown("packing.source") + ")";
  const std::string is_profile = " (it is " + p.shown("beam.profile") + ")";
  const std::string duration = p.shown("pulses.duration");
  const bool walls = !s.thermal.walls.empty();
  const std::string wall_needs =
      "applies to walls only (thermal.walls = " + p.shown("thermal.walls") +
      " names none; e.g. thermal.walls = \"z-\")";
  const KeyUse uses[] = {
      {"packing.count", source != "file", "packing.source",
       "applies to generated packings only; with packing.source = \"file\" the file gives the "
       "count"},
      {"packing.file", source == "file", "packing.source",
       "applies to packing.source = \"file\" only" + is_source},
      {"packing.radius", source == "file", "packing.source",
       "applies to packing.source = \"file\" only" + is_source},
      {"packing.radius_ratio", source == "random-overlap" || source == "lattice", "packing.source",
       "applies to packing.source = \"random-overlap\" or \"lattice\" only" + is_source},
      {"packing.solid_fraction", source == "rsa", "packing.source",
       "applies to packing.source = \"rsa\" only" + is_source},
      {"packing.seed", source == "random-overlap" || source == "rsa", "packing.source",
       "applies to packing.source = \"random-overlap\" or \"rsa\" only" + is_source},
      {"beam.decay", s.beam.profile == "exponential", "beam.profile",
       "applies to beam.profile = \"exponential\" only" + is_profile},
      {"beam.gaussian_width", s.beam.profile == "gaussian", "beam.profile",
       "applies to beam.profile = \"gaussian\" only" + is_profile},
      {"beam.seed", s.beam.sampling == "random", "beam.sampling",
       "applies to beam.sampling = \"random\" only (stratified rays are fixed)"},
      {"beam.resample", s.beam.sampling == "random", "beam.sampling",
       "applies to beam.sampling = \"random\" only (stratified rays are fixed)"},
      {"pulses.energy", duration == "\"energy\"", "pulses.duration",
       "applies to pulses.duration = \"energy\" only (it is " + duration + ")"},
      {"thermal.wall_temperature", walls, "thermal.walls", wall_needs},
      {"thermal.wall_reach", walls, "thermal.walls", wall_needs},
      {"thermal.wall_conductance", walls, "thermal.walls", wall_needs},
      {"pulses.xi", paper.duration || paper.dt || xi_always_read || p.swept("thermal.dt"),
       "pulses.duration",
       "applies to pulses.duration = \"auto\" or thermal.dt = \"paper\" only (pulses.duration is " +
           duration + ", thermal.dt is " + p.shown("thermal.dt") + ") and to `beampack converge`"},
  };
  std::vector<std::string> ignored;
  for (const KeyUse& use : uses) {
    if (use.applies || p.swept(use.decider)) continue;
    unread.push_back({use.key, use.needs});
    if (p.set_on_command_line(use.key))
      p.fail(use.key, p.shown(use.key), use.needs + ", so this run would ignore it");
    if (p.set_in_run_file(use.key) && p.differs_from_default(use.key))
      ignored.push_back(p.origins().at(use.key) + ": `" + use.key + "` = " + p.shown(use.key) +
                        ": " + use.needs + ", so this run ignores it");
  }
  return ignored;
}

// Every key, read in the order the library needs them, and the library's own checks.
RunConfig read_config(Params& p, const RunSources& sources) {
  const auto& saved_packing = sources.saved_packing;
  RunConfig c;
  read_packing(p, c.sim.packing);
  c.sim.packing.initial_temperature =
      number_up_to(p, "material.initial_temperature", 300, 0, kTemperatureCap, true);
  read_beam(p, c.sim.beam);
  read_optics(p, c.sim.optics);
  Material m;
  read_material(p, m);
  c.sim.materials = {m};
  if (saved_packing && c.sim.packing.source == "file")
    c.packing = std::make_shared<const Particles>(saved_packing(c.sim));
  check_order(p, "material.initial_temperature", c.sim.packing.initial_temperature,
              "material.vapor_temperature", m.vapor_temperature,
              " (every particle would start as vapour)");
  PaperStepUse use;
  read_pulses(p, c.sim, use);
  read_thermal(p, c.sim, use);
  c.sim.thermal.walls = read_walls(p, c.sim.packing.sample_size);
  c.sim.thermal.validate();
  c.output.frames = p.flag("output.frames", false);
  c.output.rays = p.flag("output.rays", false);
  p.check_all_used();  // first: a misspelt key is named before what it would have changed
  c.input_warnings = check_unread_keys(p, c.sim, use, sources.xi_always_read, c.unread_keys);
  if (!p.empty_file().empty())
    c.input_warnings.push_back("the run file " + p.empty_file() +
                               " sets no key: every value is the preset's, a --set's or the "
                               "default (`beampack config` prints them)");
  derive_paper_step(c, use);
  check_steps_per_crossing(p, c.sim, use.dt);
  validate_beam(c.sim.beam, c.sim.packing.sample_size);
  c.resolved = p.resolved();
  c.origins = p.origins();
  return c;
}

}  // namespace

RunConfig load_run_config(const RunSources& sources) {
  Params p;
  if (!sources.preset.empty()) {
    const Preset* found = nullptr;
    for (const Preset& preset : presets())
      if (sources.preset == preset.name) found = &preset;
    if (!found) {
      std::string list;
      for (const Preset& preset : presets())
        list += std::string(list.empty() ? "" : ", ") + preset.name;
      throw InputError("--preset " + sources.preset + ": unknown preset (known: " + list + ")");
    }
    p.merge_toml_text(found->toml, std::string("preset ") + found->name);
  }
  if (!sources.text.empty()) p.merge_toml_text(sources.text, "checkpoint");
  if (!sources.file.empty()) p.merge_toml_file(sources.file, sources.file_bytes.get());
  for (const std::string& s : sources.sets) p.merge_assignment(s);
  if (!sources.swept.empty()) p.merge_assignment(sources.swept, sources.swept_origin, true);
  try {
    return read_config(p, sources);
  } catch (const InputError& e) {  // a library check of several keys: where were they set?
    throw InputError(locate(e.what(), p.origins()));
  }
}

namespace {

// A float in the shortest form that reads back to the same double, as TOML: 0.3, 6000.0, 1e-10,
// 1e6 (toml++ 3.3 writes 17 digits, 0.29999999999999999, and a run file is read by people).
std::string toml_float(double v) {
  if (!std::isfinite(v)) return v != v ? "nan" : v > 0 ? "inf" : "-inf";
  std::array<char, 32> buf;
  std::string s(buf.data(), std::to_chars(buf.data(), buf.data() + buf.size(), v).ptr);
  const std::size_t e = s.find('e');
  if (e == std::string::npos) return s.find('.') == std::string::npos ? s + ".0" : s;
  std::string exponent = s.substr(e + 1);  // "+06" -> "6", "-10" stays
  if (exponent[0] == '+') exponent.erase(0, 1);
  const bool negative = exponent[0] == '-';
  exponent.erase(0, exponent.find_first_not_of("-0"));
  return s.substr(0, e + 1) + (negative ? "-" : "") + exponent;
}

// `name = value` as a run file line.
std::string key_line(const std::string& name, const toml::node& value) {
  if (const auto* f = value.as_floating_point()) return name + " = " + toml_float(f->get());
  std::ostringstream line;
  toml::table one;
  one.insert(name, value);
  line << one;
  return line.str();
}

}  // namespace

std::string toml_text(const toml::table& t) {
  std::ostringstream text;
  for (const auto& [name, value] : t)
    if (!value.is_table()) text << key_line(std::string(name.str()), value) << '\n';
  bool first = true;
  for (const auto& [name, value] : t) {
    if (!value.is_table()) continue;
    text << (first ? "" : "\n") << '[' << name.str() << "]\n";
    for (const auto& [key, v] : *value.as_table())
      text << key_line(std::string(key.str()), v) << '\n';
    first = false;
  }
  return text.str();
}

std::string run_file_text(const RunConfig& c) {
  toml::table read = c.resolved;
  std::ostringstream unread;
  for (const UnreadKey& u : c.unread_keys) {
    const std::size_t dot = u.key.rfind('.');
    const std::string name = u.key.substr(dot + 1);
    auto* section = read.get_as<toml::table>(u.key.substr(0, dot));
    const toml::node* value = section ? section->get(name) : nullptr;
    if (!value) continue;
    unread << "# " << u.key.substr(0, dot + 1) << key_line(name, *value) << "  # " << u.needs
           << '\n';
    section->erase(name);
  }
  std::ostringstream text;
  text << "# beampack run file: every key with the value a run would use\n" << toml_text(read);
  if (!unread.str().empty())
    text << "\n# Keys this scene does not read, with the values they would take; to use one once\n"
            "# what it needs holds, put it under its [section] without the section's name:\n"
         << unread.str();
  return text.str();
}

void warn_of_input(const std::vector<const RunConfig*>& configs) {
  std::set<std::string> said;
  for (const RunConfig* c : configs)
    for (const std::string& line : c->input_warnings)
      if (said.insert(line).second) std::fprintf(stderr, "beampack: warning: %s\n", line.c_str());
}

// Whether the message already says where: "path:line: ..." (a packing file's row names its own
// line; a key it mentions, such as sample.size in a radius limit, did not put it there).
bool starts_with_location(const std::string& message) {
  const std::size_t colon = message.find(": ");
  if (colon == std::string::npos) return false;
  std::size_t digits = colon;
  while (digits > 0 && std::isdigit(static_cast<unsigned char>(message[digits - 1]))) --digits;
  return digits < colon && digits > 0 && message[digits - 1] == ':';
}

std::string locate(const std::string& message, const std::map<std::string, std::string>& origins) {
  if (starts_with_location(message)) return message;
  auto is_key_char = [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.';
  };
  std::size_t first = std::string::npos;
  std::string at;
  for (const auto& [key, where] : origins) {
    if (message.starts_with(where + ":")) return message;
    for (std::size_t i = message.find(key); i < first; i = message.find(key, i + 1)) {
      const std::size_t end = i + key.size();
      if ((i == 0 || !is_key_char(message[i - 1])) &&
          (end == message.size() || !is_key_char(message[end]))) {
        first = i, at = where;
        break;
      }
    }
  }
  return first == std::string::npos ? message : at + ": " + message;
}

double paper_step(const PackingSpec& packing, double xi, const Particles* particles) {
  return paper_time_step(xi, particles ? median_radius(*particles) : packing_radius(packing));
}

std::unique_ptr<Simulation> start_simulation(const RunConfig& config,
                                             const std::function<void(std::size_t)>& counted) {
  auto checked = [&](std::size_t particles) {
    refuse_beyond_memory(config.sim, machine_memory(), particles);
    if (counted) counted(particles);
  };
  try {
    // A file's particles are counted once read: here, unless the configuration read them.
    if (!config.packing && config.sim.packing.source == "file") {
      Particles read = make_packing(config.sim.packing);
      checked(read.size());
      return std::make_unique<Simulation>(config.sim, std::move(read));
    }
    checked(config.packing ? config.packing->size() : config.sim.packing.count);
    if (config.packing) return std::make_unique<Simulation>(config.sim, *config.packing);
    return std::make_unique<Simulation>(config.sim);
  } catch (const InputError& e) {
    throw InputError(locate(e.what(), config.origins));
  }
}

}  // namespace beampack::tools
