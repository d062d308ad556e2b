#pragma once
// A run's configuration: defaults, then a preset, then a run file, then --set overrides, read
// through Params into the library's SimulationSpec.
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "engine/memory_need.h"
#include "engine/simulation.h"
#include "tools/params.h"

namespace beampack::tools {

struct OutputSpec {
  bool frames = false;  // output.frames: particles_NNNN.vtp after every pulse, with particles.pvd
  bool rays = false;    // output.rays: rays_NNNN.vtp, the paths of each pulse's rays
};

// A key of the run file this scene does not read, and what would make it apply.
struct UnreadKey {
  std::string key, needs;
};

struct RunConfig {
  SimulationSpec sim;
  OutputSpec output;
  toml::table resolved;  // every key with the value used
  double xi = 0.05;      // pulses.xi: the paper's ray time step is xi R / c (paper_step)
  // A packing file's particles when the configuration had to read them (its median radius for
  // xi R / c), so that the simulation does not read the file again; null otherwise.
  std::shared_ptr<const Particles> packing;
  std::map<std::string, std::string> origins;  // key -> where a layer set it ("run.toml:7")
  // What the input asks that this scene ignores: keys a run file sets to other values than their
  // defaults that it does not read, a run file that sets no key. One line each, for the command to
  // print as warnings (beampack: warning: ...).
  std::vector<std::string> input_warnings;
  // Every key this scene does not read (whoever set it): `beampack config` prints them apart.
  std::vector<UnreadKey> unread_keys;
};

struct RunSources {
  std::string file;               // RUN.toml ("" for none)
  std::string preset;             // --preset NAME ("" for none)
  std::vector<std::string> sets;  // --set KEY=VALUE, in order
  std::string text;               // a complete run file held in a checkpoint ("" for none)
  // `file`'s bytes once read (read_once): sweep and converge resolve it for every value and rung,
  // and a pipe (`run <(...)`, `... | sweep /dev/stdin`) can be read only once.
  std::shared_ptr<const std::string> file_bytes;
  void read_once() {
    if (!file.empty() && !file_bytes)
      file_bytes = std::make_shared<std::string>(read_run_file(file));
  }
  // KEY=VALUE applied after the --set list by sweep and converge, and named in messages as
  // `swept_origin` ("--param K --values V") rather than as a --set the user never typed.
  std::string swept, swept_origin;
  // A file packing's particles for the resolved spec, when they need not be read from the file:
  // a resumed run's, from its checkpoint (which holds them), so that the run continues without
  // its packing file. Called only for a file packing. Empty: read the file.
  std::function<Particles(const SimulationSpec&)> saved_packing;
  // pulses.xi is read whatever the scene: converge's time-step ladder is made of xi R / c, and
  // `beampack config` may print a run file for converge. Otherwise a --set of it is refused when
  // neither pulses.duration = "auto" nor thermal.dt = "paper" uses it.
  bool xi_always_read = false;
};

// InputError (exit code 2) for any bad key, type or value, naming file and line.
RunConfig load_run_config(const RunSources& sources);

// The text `beampack config` prints: the resolved run file, and the keys this scene does not read
// apart, as comments with their values (a run of the file then warns of none of them).
std::string run_file_text(const RunConfig& config);

// A resolved run file as TOML: top-level keys, then one [section] of keys per table; numbers in
// the shortest form that reads back to the same double.
std::string toml_text(const toml::table& t);

// The configurations' input_warnings on stderr as warnings, each line once (a sweep's runs share
// their run file).
void warn_of_input(const std::vector<const RunConfig*>& configs);

// `message` with the place that set the first key it names ("run.toml:7: ..."), unless it
// already starts with one: for errors found after the run file was read.
std::string locate(const std::string& message, const std::map<std::string, std::string>& origins);

// The simulation of a configuration (refused beyond this machine's memory); an InputError from
// its set-up (the packing file, the thermal masses) names where the key it mentions was set.
// `counted`, when given, hears the particle count once it is known and passes the memory check
// (a file's once it is read), before the packing, its contacts and the ray scene are built.
std::unique_ptr<Simulation> start_simulation(const RunConfig& config,
                                             const std::function<void(std::size_t)>& counted = {});

// xi R / c, the paper's ray time step, with R the packing's radius: for a file, the median of
// `particles`' radii (read from the file when null).
double paper_step(const PackingSpec& packing, double xi, const Particles* particles = nullptr);

// least_memory_need, machine_memory and refuse_beyond_memory: engine/memory_need.h (a Simulation
// checks them too; start_simulation checks them before it reads a packing file whole).

// Named presets: TOML text.
struct Preset {
  const char* name;
  const char* summary;
  const char* toml;
};
const std::vector<Preset>& presets();

}  // namespace beampack::tools
