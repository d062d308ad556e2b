#include "fuzz/fuzz_checks.h"

#include <unistd.h>

#include <cmath>
#include <complex>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <system_error>
#include <vector>

#include "geometry/error.h"
#include "geometry/packing.h"
#include "tools/run_config.h"

namespace beampack::fuzz {
namespace {

namespace fs = std::filesystem;

// The scratch files this process wrote, removed when it exits normally.
struct ScratchFiles {
  std::vector<fs::path> paths;
  ~ScratchFiles() {
    std::error_code ignored;
    for (const fs::path& p : paths) fs::remove(p, ignored);
  }
};

// One file per process and kind, rewritten for every input: libFuzzer runs inputs one at a
// time, and ctest may run the two targets (two processes) side by side.
std::string scratch_file(const char* kind, std::span<const std::uint8_t> bytes) {
  static ScratchFiles written;
  const fs::path path =
      fs::temp_directory_path() / ("beampack_fuzz_" + std::to_string(::getpid()) + "_" + kind);
  if (std::find(written.paths.begin(), written.paths.end(), path) == written.paths.end())
    written.paths.push_back(path);
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(bytes.data()),
            static_cast<std::streamsize>(bytes.size()));
  out.close();
  if (!out) throw std::runtime_error("fuzz harness: cannot write " + path.string());
  return path.string();
}

// Collects the names of non-finite values.
class FiniteCheck {
 public:
  void operator()(const char* name, double v) {
    if (!std::isfinite(v)) bad_ << (bad_.tellp() > 0 ? ", " : "") << name << " = " << v;
  }
  void operator()(const char* name, std::complex<double> v) {
    (*this)(name, v.real());
    (*this)(name, v.imag());
  }
  std::string report() const { return bad_.str(); }

 private:
  std::ostringstream bad_;
};

std::string check_spec(const SimulationSpec& s) {
  FiniteCheck f;
  f("packing.sample_size", s.packing.sample_size);
  f("packing.radius_ratio", s.packing.radius_ratio);
  f("packing.solid_fraction", s.packing.solid_fraction);
  f("packing.file_radius", s.packing.file_radius);
  f("packing.initial_temperature", s.packing.initial_temperature);
  f("beam.power", s.beam.power);
  f("beam.diameter_fraction", s.beam.diameter_fraction);
  f("beam.decay", s.beam.decay);
  f("beam.gaussian_width", s.beam.gaussian_width);
  for (int a = 0; a < 3; ++a) f("beam.direction", s.beam.direction[a]);
  for (const MaterialOptics& m : s.optics.materials) {
    f("optics.n_solid", m.n_solid);
    f("optics.n_liquid", m.n_liquid);
    f("optics.mu_hat", m.mu_hat);
  }
  f("optics.cutoff", s.optics.cutoff);
  for (const Material& m : s.materials) {
    f("material.density", m.density);
    f("material.c_solid", m.c_solid);
    f("material.c_liquid", m.c_liquid);
    f("material.conductivity", m.conductivity);
    f("material.melt_temperature", m.melt_temperature);
    f("material.vapor_temperature", m.vapor_temperature);
    f("material.latent_melt", m.latent_melt);
    f("material.latent_solidify", m.latent_solidify);
    f("material.latent_vapor", m.latent_vapor);
  }
  f("thermal.phi", s.thermal.phi);
  f("thermal.time_scaling", s.thermal.time_scaling);
  f("thermal.tolerance", s.thermal.tolerance);
  f("pulses.duration", s.pulses.duration);
  f("pulses.period", s.pulses.period);
  f("thermal.dt", s.dt);
  std::string bug = f.report();
  if (!bug.empty()) return "non-finite value in the resolved spec: " + bug;
  // Values the library divides by or takes as a length of time: accepted means usable.
  if (!(s.pulses.duration > 0)) return "accepted pulses.duration <= 0";
  if (!(std::abs(s.beam.direction.norm() - 1.0) <= 1e-9))
    return "beam.direction is not a unit vector";
  return "";
}

// Every floating-point value of the resolved configuration (summary.json's `config`) is finite.
std::string check_resolved(const toml::table& table, const std::string& prefix = "") {
  std::string bug;
  for (const auto& [key, node] : table) {
    const std::string name = prefix + std::string(key.str());
    if (const toml::table* sub = node.as_table()) bug = check_resolved(*sub, name + ".");
    else if (const auto* v = node.as_floating_point(); v && !std::isfinite(v->get()))
      bug = "resolved `" + name + "` is not finite";
    if (!bug.empty()) break;
  }
  return bug;
}

std::string particle_bug(const Particles& p) {
  for (std::size_t i = 0; i < p.size(); ++i) {
    const Vec3& c = p.centre[i];
    const double r = p.radius[i];
    std::ostringstream where;
    where << "particle " << i << " (" << c.transpose() << ", r = " << r << "): ";
    if (!c.allFinite() || !std::isfinite(r)) return where.str() + "not finite";
    if (!(r > 0)) return where.str() + "radius not > 0";
    const double volume = p.volume(i);
    if (!(volume > 0) || !std::isfinite(volume)) return where.str() + "volume not finite and > 0";
    for (int a = 0; a < 3; ++a)
      if (!std::isfinite(c[a] - r) || !std::isfinite(c[a] + r))
        return where.str() + "bounding box not finite";
  }
  return "";
}

template <class F>
Outcome guarded(F&& body) {
  Outcome o;
  try {
    o.bug = body();
    o.accepted = true;
  } catch (const InputError& e) {
    o.input_error = e.what();
    if (o.input_error.empty()) o.bug = "InputError with an empty message";
  } catch (const std::exception& e) {
    o.bug = std::string("unexpected exception: ") + e.what();
  } catch (...) {
    o.bug = "unexpected exception of unknown type";
  }
  return o;
}

}  // namespace

Outcome check_run_file(std::span<const std::uint8_t> bytes) {
  std::size_t nul = 0;
  while (nul < bytes.size() && bytes[nul] != 0) ++nul;
  tools::RunSources sources;
  sources.file = scratch_file("run.toml", bytes.first(nul));
  if (nul < bytes.size()) {
    std::string rest(reinterpret_cast<const char*>(bytes.data()) + nul + 1, bytes.size() - nul - 1);
    std::istringstream lines(rest);
    for (std::string line; std::getline(lines, line);) {
      if (line.rfind("--preset ", 0) == 0) sources.preset = line.substr(9);
      else sources.sets.push_back(line);
    }
  }
  return guarded([&] {
    const tools::RunConfig c = tools::load_run_config(sources);
    std::string bug = check_spec(c.sim);
    if (bug.empty()) bug = check_resolved(c.resolved);
    return bug;
  });
}

Outcome check_packing_file(std::span<const std::uint8_t> bytes) {
  const std::string path = scratch_file("packing.txt", bytes);
  Outcome four = guarded([&] { return particle_bug(read_packing_file(path, 0.0)); });
  if (!four.bug.empty()) return four;
  Outcome three = guarded([&] { return particle_bug(read_packing_file(path, 1e-5)); });
  if (!three.bug.empty()) three.bug = "(x y z, radius 1e-5) " + three.bug;
  return three.bug.empty() ? four : three;  // the x y z r reading, unless x y z found a bug
}

int report(const Outcome& outcome, const char* target) {
  if (outcome.bug.empty()) return 0;
  std::fprintf(stderr, "beampack fuzz bug (%s): %s\n", target, outcome.bug.c_str());
  std::abort();
}

}  // namespace beampack::fuzz
