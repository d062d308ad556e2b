#pragma once
// Output files of a run (INTERFACE.md). Every file is written to a temporary name in the same
// directory and renamed into place, so an interrupted run never leaves a half-written file; the
// file is synced to disk before its rename and the directory after, so neither does a power loss.
#include <functional>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "engine/tracer.h"
#include "geometry/particles.h"

namespace beampack::tools {

// An output file and what fills it.
struct OutputFile {
  std::string path;
  std::function<void(std::ostream&)> fill;
};

// Writes through `fill`, then renames; RunError if it cannot be written or synced to disk.
void write_atomically(const std::string& path, const std::function<void(std::ostream&)>& fill);
// A set of files that belong together (a run's particles.csv and its summary.json): every one is
// written to its temporary first, and only when all are whole are they renamed into place, in
// order. A failure while writing (a full disk) replaces none of them.
void write_atomically(const std::vector<OutputFile>& files);

// A file that grows by whole lines while a run goes (history.csv: a row as each pulse ends, so a
// killed run keeps its rows and `tail -F` follows a run). Its first `append` writes the text so
// far whole, atomically (an earlier run's or a killed one's file is replaced, not continued);
// each later one appends its text with one write(), so the file never holds part of a line but
// where the disk filled. RunError naming the file when a write fails. A run's end still replaces
// it whole with write_atomically.
class GrowingFile {
 public:
  explicit GrowingFile(std::string path) : path_(std::move(path)) {}
  ~GrowingFile();
  GrowingFile(const GrowingFile&) = delete;
  GrowingFile& operator=(const GrowingFile&) = delete;
  // `whole`: the file's text so far, `tail` included; `tail`: what this call adds to it.
  void append(const std::string& whole, const std::string& tail);

 private:
  std::string path_;
  int fd_ = -1;
};

// id,x,y,z,r,temperature_K,phase,absorbed_J for every particle, vaporised ones included (the
// file refers to p and absorbed_J: they must outlive the write).
OutputFile particles_csv(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J);

// A ParaView PolyData frame: points with radius, temperature, phase, absorbed energy, alive.
void write_particles_vtp(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J);
// Ray segments as lines, with the energy each carried.
void write_rays_vtp(const std::string& path, const std::vector<RaySegment>& segments);
// The .pvd series index over frames (file name relative to the .pvd, time).
void write_pvd(const std::string& path, const std::vector<std::pair<std::string, double>>& frames);

// The shortest text that reads back as the same double (std::to_chars): 0.064, not
// 0.064000000000000001.
std::string exact(double v);
// A CSV cell: exact(v), or empty when there is no value (a scene without particles has no peak).
std::string exact(std::optional<double> v);
// Console text: v through a printf `format` ("%.3g K"), or `none` when there is no value.
std::string shown(std::optional<double> v, const char* format, const char* none);

}  // namespace beampack::tools
