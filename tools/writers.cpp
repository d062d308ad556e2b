#include "tools/writers.h"

#include <cerrno>
#include <charconv>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <set>
#include <system_error>

#include <fcntl.h>
#include <unistd.h>

#include "geometry/error.h"
#include "tools/quit_cleanup.h"

namespace beampack::tools {

std::string exact(double v) {
  char buf[32];
  const std::to_chars_result r = std::to_chars(buf, buf + sizeof buf, v);  // shortest round trip
  return std::string(buf, r.ptr);
}

std::string exact(std::optional<double> v) {
  return v ? exact(*v) : "";
}

std::string shown(std::optional<double> v, const char* format, const char* none) {
  if (!v) return none;
  char text[64];
  std::snprintf(text, sizeof text, format, *v);
  return text;
}

namespace {

// A file being staged: its temporary beside it, registered for a second interrupt to remove.
struct Staged {
  std::string path, tmp;
  QuitRemovesFile on_quit;
  explicit Staged(const std::string& p) : path(p), tmp(temporary_path(p)), on_quit(tmp) {}
};

void remove_temporaries(const std::vector<std::unique_ptr<Staged>>& staged) {
  std::error_code ec;
  for (const auto& s : staged) std::filesystem::remove(s->tmp, ec);
}

// fsync of the file or directory at `path` (`flags` open it): 0, or the errno of the failure.
int sync_to_disk(const std::string& path, int flags) {
  const int fd = ::open(path.c_str(), flags | O_CLOEXEC);
  if (fd < 0) return errno;
  const int error = ::fsync(fd) == 0 ? 0 : errno;
  ::close(fd);
  return error;
}

std::string error_text(int error) {
  return std::generic_category().message(error);
}

void stage(const Staged& s, const std::function<void(std::ostream&)>& fill) {
  std::ofstream out(s.tmp, std::ios::binary);
  // A failed run, not bad input: the command checked --out was writable before it started.
  if (!out) throw RunError("output file \"" + s.path + "\": cannot write in its directory");
  fill(out);
  out.close();
  if (!out) throw RunError("output file \"" + s.path + "\": write failed (disk full?)");
  // The data on the disk before the rename: the file system may write the rename first, and a
  // power loss between the two can leave the renamed file empty.
  // A file system that cannot sync (EINVAL, ENOTSUP) has nothing to do; EIO or ENOSPC now is a
  // write that failed.
  const int error = sync_to_disk(s.tmp, O_RDONLY);
  if (error != 0 && error != EINVAL && error != ENOTSUP && error != EOPNOTSUPP)
    throw RunError("output file \"" + s.path + "\": fsync failed: " + error_text(error));
}

// The renames on the disk: a directory's entries are synced as a file's data is. Best effort:
// the files are whole and renamed by now, and some file systems (network, FUSE) or a folder
// opened without read permission refuse it; a run is not failed for its folder's durability.
void sync_directories(const std::vector<std::unique_ptr<Staged>>& staged) {
  std::set<std::string> dirs;
  for (const auto& s : staged) {
    const std::string dir = std::filesystem::path(s->path).parent_path().string();
    dirs.insert(dir.empty() ? "." : dir);
  }
  for (const std::string& dir : dirs) sync_to_disk(dir, O_RDONLY | O_DIRECTORY);
}

}  // namespace

void write_atomically(const std::vector<OutputFile>& files) {
  std::vector<std::unique_ptr<Staged>> staged;
  try {  // an error or an interrupt while filling: no file is replaced, no temporary is left
    for (const OutputFile& f : files) {
      staged.push_back(std::make_unique<Staged>(f.path));
      stage(*staged.back(), f.fill);
    }
  } catch (...) {
    remove_temporaries(staged);
    throw;
  }
  for (std::size_t k = 0; k < staged.size(); ++k) {
    std::error_code ec;
    std::filesystem::rename(staged[k]->tmp, staged[k]->path, ec);
    if (!ec) continue;
    remove_temporaries(staged);
    throw RunError("output file \"" + staged[k]->path + "\": rename failed: " + ec.message() +
                   (k > 0 ? " (the files before it in the set were replaced)" : ""));
  }
  sync_directories(staged);
}

void write_atomically(const std::string& path, const std::function<void(std::ostream&)>& fill) {
  write_atomically({OutputFile{path, fill}});
}

GrowingFile::~GrowingFile() {
  if (fd_ >= 0) ::close(fd_);
}

void GrowingFile::append(const std::string& whole, const std::string& tail) {
  if (fd_ < 0) {
    write_atomically(path_, [&](std::ostream& o) { o << whole; });
    fd_ = ::open(path_.c_str(), O_WRONLY | O_APPEND | O_CLOEXEC);
    if (fd_ < 0)
      throw RunError("output file \"" + path_ +
                     "\": cannot reopen to append: " + error_text(errno));
    return;
  }
  for (std::size_t done = 0; done < tail.size();) {
    const ssize_t n = ::write(fd_, tail.data() + done, tail.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0)
      throw RunError("output file \"" + path_ +
                     "\": write failed: " + error_text(n < 0 ? errno : ENOSPC));
    done += static_cast<std::size_t>(n);
  }
}

OutputFile particles_csv(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J) {
  return {path, [&p, &absorbed_J](std::ostream& out) {
            out << "id,x,y,z,r,temperature_K,phase,absorbed_J\n";
            for (std::size_t i = 0; i < p.size(); ++i) {
              const Vec3& c = p.centre[i];
              out << i << ',' << exact(c.x()) << ',' << exact(c.y()) << ',' << exact(c.z()) << ','
                  << exact(p.radius[i]) << ',' << exact(p.temperature[i]) << ','
                  << phase_name(p.phase[i]) << ','
                  << exact(i < absorbed_J.size() ? absorbed_J[i] : 0.0) << '\n';
            }
          }};
}

namespace {

template <class Value>
void data_array(std::ostream& out, const char* type, const char* name, int components,
                std::size_t n, Value&& value) {
  out << "        <DataArray type=\"" << type << "\" Name=\"" << name << "\" NumberOfComponents=\""
      << components << "\" format=\"ascii\">\n";
  for (std::size_t i = 0; i < n; ++i) out << "          " << value(i) << '\n';
  out << "        </DataArray>\n";
}

void vtp_header(std::ostream& out, std::size_t points, std::size_t verts, std::size_t lines) {
  out << "<?xml version=\"1.0\"?>\n"
         "<!-- written by beampack -->\n"
         "<VTKFile type=\"PolyData\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
         "  <PolyData>\n"
      << "    <Piece NumberOfPoints=\"" << points << "\" NumberOfVerts=\"" << verts
      << "\" NumberOfLines=\"" << lines << "\" NumberOfStrips=\"0\" NumberOfPolys=\"0\">\n";
}

void vtp_footer(std::ostream& out) {
  out << "    </Piece>\n  </PolyData>\n</VTKFile>\n";
}

// Cells: connectivity 0..n-1 in groups of `per_cell` points.
void cells(std::ostream& out, const char* kind, std::size_t count, int per_cell) {
  out << "      <" << kind << ">\n";
  data_array(out, "Int64", "connectivity", 1, count * per_cell, [](std::size_t i) { return i; });
  data_array(out, "Int64", "offsets", 1, count,
             [per_cell](std::size_t i) { return (i + 1) * per_cell; });
  out << "      </" << kind << ">\n";
}

}  // namespace

void write_particles_vtp(const std::string& path, const Particles& p,
                         const std::vector<double>& absorbed_J) {
  write_atomically(path, [&](std::ostream& out) {
    const std::size_t n = p.size();
    vtp_header(out, n, n, 0);
    out << "      <Points>\n";
    data_array(out, "Float64", "Points", 3, n, [&](std::size_t i) {
      return exact(p.centre[i].x()) + " " + exact(p.centre[i].y()) + " " + exact(p.centre[i].z());
    });
    out << "      </Points>\n";
    cells(out, "Verts", n, 1);
    out << "      <PointData Scalars=\"temperature\">\n";
    data_array(out, "Float64", "radius", 1, n, [&](std::size_t i) { return exact(p.radius[i]); });
    data_array(out, "Float64", "temperature", 1, n,
               [&](std::size_t i) { return exact(p.temperature[i]); });
    data_array(out, "Int32", "phase", 1, n, [&](std::size_t i) { return int(p.phase[i]); });
    data_array(out, "Float64", "absorbed_energy", 1, n,
               [&](std::size_t i) { return exact(i < absorbed_J.size() ? absorbed_J[i] : 0.0); });
    data_array(out, "Int32", "alive", 1, n, [&](std::size_t i) { return int(p.alive[i]); });
    out << "      </PointData>\n";
    vtp_footer(out);
  });
}

void write_rays_vtp(const std::string& path, const std::vector<RaySegment>& segments) {
  write_atomically(path, [&](std::ostream& out) {
    const std::size_t n = segments.size();
    vtp_header(out, 2 * n, 0, n);
    out << "      <Points>\n";
    data_array(out, "Float64", "Points", 3, 2 * n, [&](std::size_t k) {
      const Vec3& v = k % 2 ? segments[k / 2].to : segments[k / 2].from;
      return exact(v.x()) + " " + exact(v.y()) + " " + exact(v.z());
    });
    out << "      </Points>\n";
    cells(out, "Lines", n, 2);
    out << "      <CellData Scalars=\"energy\">\n";
    data_array(out, "Float64", "energy", 1, n,
               [&](std::size_t i) { return exact(segments[i].energy); });
    out << "      </CellData>\n";
    vtp_footer(out);
  });
}

void write_pvd(const std::string& path, const std::vector<std::pair<std::string, double>>& frames) {
  write_atomically(path, [&](std::ostream& out) {
    out << "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  "
           "<Collection>\n";
    for (const auto& [file, time] : frames)
      out << "    <DataSet timestep=\"" << exact(time) << "\" part=\"0\" file=\"" << file
          << "\"/>\n";
    out << "  </Collection>\n</VTKFile>\n";
  });
}

}  // namespace beampack::tools
