#include "geometry/packing.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <sstream>
#include <vector>

#include "geometry/cell_grid.h"
#include "geometry/error.h"
#include "geometry/random.h"

namespace beampack {
namespace {

void require(bool ok, const std::string& message) {
  if (!ok) throw InputError(message);
}

std::string str(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

void check_common(std::size_t count, double size) {
  require(count <= 100'000'000, "packing.count = " + std::to_string(count) + ": must be <= 1e8");
  require(std::isfinite(size) && size > 0, "sample.size = " + str(size) + ": must be > 0");
}

// Interleaves the low 21 bits of x, y, z (a Morton code).
std::uint64_t morton(std::uint64_t x, std::uint64_t y, std::uint64_t z) {
  auto spread = [](std::uint64_t v) {
    v &= 0x1fffff;
    v = (v | v << 32) & 0x1f00000000ffffull;
    v = (v | v << 16) & 0x1f0000ff0000ffull;
    v = (v | v << 8) & 0x100f00f00f00f00full;
    v = (v | v << 4) & 0x10c30c30c30c30c3ull;
    v = (v | v << 2) & 0x1249249249249249ull;
    return v;
  };
  return spread(x) | spread(y) << 1 | spread(z) << 2;
}

// Numbers generated particles along a Morton curve: neighbours in space become neighbours in
// memory, which is what the contact search, the conduction matrix and the scene read together.
// A deterministic function of the centres, so a seed still gives one packing everywhere.
void sort_spatially(Particles& p, double size) {
  const std::size_t n = p.size();
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keys(n);
  const double scale = double((1u << 21) - 1) / size;
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3 q = (p.centre[i] * scale).cwiseMax(0.0).cwiseMin(double((1u << 21) - 1));
    keys[i] = {morton(std::uint64_t(q.x()), std::uint64_t(q.y()), std::uint64_t(q.z())),
               static_cast<std::uint32_t>(i)};
  }
  std::sort(keys.begin(), keys.end());
  Particles sorted;
  sorted.reserve(n);
  for (const auto& [key, i] : keys) sorted.add(p.centre[i], p.radius[i], p.material[i], p.temperature[i]);
  p = std::move(sorted);
}

}  // namespace

Particles random_overlap_packing(std::size_t count, double size, double radius_ratio,
                                 std::uint64_t seed) {
  check_common(count, size);
  require(std::isfinite(radius_ratio) && radius_ratio > 0,
          "packing.radius_ratio = " + str(radius_ratio) + ": must be > 0");
  Particles p;
  if (count == 0) return p;
  PackingSpec spec;
  spec.count = count, spec.sample_size = size, spec.radius_ratio = radius_ratio;
  const double r = packing_radius(spec);
  Rng rng(seed);
  p.reserve(count);
  for (std::size_t i = 0; i < count; ++i) {
    const double x = rng.uniform(0, size), y = rng.uniform(0, size), z = rng.uniform(0, size);
    p.add({x, y, z}, r);
  }
  sort_spatially(p, size);
  return p;
}

Particles rsa_packing(std::size_t count, double size, double solid_fraction, std::uint64_t seed) {
  check_common(count, size);
  require(std::isfinite(solid_fraction) && solid_fraction > 0 && solid_fraction < 0.5,
          "packing.solid_fraction = " + str(solid_fraction) +
              ": must be in (0, 0.5); random sequential addition jams near 0.38");
  Particles p;
  if (count == 0) return p;
  PackingSpec spec;
  spec.source = "rsa", spec.count = count, spec.sample_size = size;
  spec.solid_fraction = solid_fraction;
  const double r = packing_radius(spec);
  require(2 * r < size, "packing.solid_fraction = " + str(solid_fraction) +
                            ": spheres wider than the sample; raise packing.count");
  Box centres;
  centres.grow(Vec3::Constant(r), 0.0);
  centres.grow(Vec3::Constant(size - r), 0.0);
  CellGrid grid(centres, 2 * r, count);
  Rng rng(seed);
  // Bounded work: a run of failures this long means the packing is jammed for practical purposes.
  const std::size_t max_failures_in_a_row = 200'000;
  p.reserve(count);
  std::size_t failures = 0;
  while (p.size() < count) {
    const Vec3 c{rng.uniform(r, size - r), rng.uniform(r, size - r), rng.uniform(r, size - r)};
    bool overlaps = false;
    grid.for_each_neighbour(c, [&](std::uint32_t j) {
      overlaps = overlaps || (p.centre[j] - c).squaredNorm() < 4 * r * r;
    });
    if (overlaps) {
      if (++failures >= max_failures_in_a_row) {
        throw InputError("packing.solid_fraction = " + str(solid_fraction) +
                         ": rsa placed only " + std::to_string(p.size()) + " of " +
                         std::to_string(count) + " spheres (reached " +
                         str(solid_fraction * double(p.size()) / double(count)) + ") before " +
                         std::to_string(max_failures_in_a_row) +
                         " failed tries in a row; use a lower fraction (RSA jams near 0.38)");
      }
      continue;
    }
    failures = 0;
    grid.insert(c, static_cast<std::uint32_t>(p.add(c, r)));
  }
  sort_spatially(p, size);
  return p;
}

Particles lattice_packing(std::size_t count, double size, double radius_ratio) {
  check_common(count, size);
  require(std::isfinite(radius_ratio) && radius_ratio > 0,
          "packing.radius_ratio = " + str(radius_ratio) + ": must be > 0");
  const auto n = static_cast<std::size_t>(std::llround(std::cbrt(double(count))));
  require(n * n * n == count, "packing.count = " + std::to_string(count) +
                                  ": a lattice needs a cube number (n^3, e.g. " +
                                  std::to_string(n * n * n) + ")");
  Particles p;
  const double a = size / double(std::max<std::size_t>(n, 1));
  p.reserve(count);
  for (std::size_t k = 0; k < n; ++k)
    for (std::size_t j = 0; j < n; ++j)
      for (std::size_t i = 0; i < n; ++i)
        p.add({(i + 0.5) * a, (j + 0.5) * a, (k + 0.5) * a}, radius_ratio * a);
  return p;
}

namespace {

std::vector<std::string_view> split_columns(std::string_view line) {
  std::vector<std::string_view> cols;
  std::size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == ',' || line[i] == '\r'))
      ++i;
    std::size_t j = i;
    while (j < line.size() && !(line[j] == ' ' || line[j] == '\t' || line[j] == ',' || line[j] == '\r'))
      ++j;
    if (j > i) cols.push_back(line.substr(i, j - i));
    i = j;
  }
  return cols;
}

bool parse_number(std::string_view text, double& value) {
  if (!text.empty() && text.front() == '+') text.remove_prefix(1);
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  return ec == std::errc() && end == text.data() + text.size();
}

// A header names the columns: no column of it is a number. A data line with a typo in its first
// column is not one, and is reported instead of skipped.
bool is_header(const std::vector<std::string_view>& cols) {
  double probe;
  return std::none_of(cols.begin(), cols.end(), [&](std::string_view c) { return parse_number(c, probe); });
}

}  // namespace

Particles read_packing_file(const std::string& path, double default_radius) {
  // Checked before opening: a FIFO would block the open, a device would be read without end.
  std::error_code ec;
  require(!std::filesystem::exists(path, ec) || std::filesystem::is_regular_file(path, ec),
          "packing.file = \"" + path + "\": not a regular file (a directory, FIFO or device)");
  std::ifstream in(path);
  require(in.good(), "packing.file = \"" + path + "\": cannot open for reading");
  const std::size_t need = default_radius > 0 ? 3 : 4;
  const std::string layout = need == 4 ? "x y z r" : "x y z";
  Particles p;
  std::string line;
  bool seen_data = false, seen_header = false;
  for (std::size_t line_no = 1; std::getline(in, line); ++line_no) {
    std::string_view view(line);
    if (auto hash = view.find('#'); hash != std::string_view::npos) view = view.substr(0, hash);
    const auto cols = split_columns(view);
    if (cols.empty()) continue;
    const std::string where = path + ":" + std::to_string(line_no) + ": ";
    double v[4] = {0, 0, 0, default_radius};
    if (!seen_data && is_header(cols)) {  // one header line (no column a number) before the data
      require(!seen_header, where + "a second header line; one is allowed, before the data");
      seen_header = true;
      continue;
    }
    seen_data = true;
    require(cols.size() == need, where + "expected " + std::to_string(need) + " columns (" +
                                     layout + "), found " + std::to_string(cols.size()));
    for (std::size_t k = 0; k < need; ++k) {
      require(parse_number(cols[k], v[k]),
              where + "column " + std::to_string(k + 1) + " '" + std::string(cols[k]) +
                  "' is not a number");
      require(std::isfinite(v[k]), where + "column " + std::to_string(k + 1) + " '" +
                                       std::string(cols[k]) + "' is not finite");
    }
    require(v[3] > 0, where + "radius r = " + str(v[3]) + ": must be > 0");
    // Finite numbers can still make a sphere the physics cannot hold (found by fuzz/): a radius
    // whose volume, hence mass, rounds to 0 or overflows, or a centre +- r beyond the doubles.
    const double volume = 4.0 / 3.0 * std::numbers::pi * v[3] * v[3] * v[3];
    require(volume > 0 && std::isfinite(volume),
            where + "radius r = " + str(v[3]) + ": its volume " + str(volume) +
                " is not a positive finite double (|r| must be within ~1e-100 .. 1e100)");
    for (int k = 0; k < 3; ++k)
      require(std::isfinite(std::abs(v[k]) + v[3]),
              where + "centre +- radius overflows in column " + std::to_string(k + 1));
    p.add({v[0], v[1], v[2]}, v[3]);
  }
  require(!in.bad(), "packing.file = \"" + path + "\": read error");
  // An empty bed is allowed when asked for (packing.count = 0), not from a file that lost its data.
  require(p.size() > 0, "packing.file = \"" + path + "\": holds no particle (" +
                            (seen_header ? "a header line only" : "no data line") + ")");
  return p;
}

void write_packing_file(const std::string& path, const Particles& particles) {
  std::ofstream out(path);
  require(out.good(), "cannot open \"" + path + "\" for writing");
  out << "# x y z r\n";
  char buf[160];
  for (std::size_t i = 0; i < particles.size(); ++i) {
    const Vec3& c = particles.centre[i];
    std::snprintf(buf, sizeof buf, "%.17g %.17g %.17g %.17g\n", c.x(), c.y(), c.z(),
                  particles.radius[i]);
    out << buf;
  }
  require(out.good(), "write error on \"" + path + "\"");
}

double packing_radius(const PackingSpec& s) {
  const double n = double(std::max<std::size_t>(s.count, 1));
  if (s.source == "rsa") return s.sample_size * std::cbrt(3.0 * s.solid_fraction / (4.0 * std::numbers::pi * n));
  if (s.source == "file") return s.file_radius > 0 ? s.file_radius : s.sample_size / 100;
  return s.radius_ratio * s.sample_size / std::cbrt(n);
}

Particles make_packing(const PackingSpec& spec) {
  Particles p;
  if (spec.source == "random-overlap")
    p = random_overlap_packing(spec.count, spec.sample_size, spec.radius_ratio, spec.seed);
  else if (spec.source == "rsa")
    p = rsa_packing(spec.count, spec.sample_size, spec.solid_fraction, spec.seed);
  else if (spec.source == "lattice")
    p = lattice_packing(spec.count, spec.sample_size, spec.radius_ratio);
  else if (spec.source == "file")
    p = read_packing_file(spec.file, spec.file_radius);
  else
    throw InputError("packing.source = \"" + spec.source +
                     "\": must be one of random-overlap, rsa, lattice, file");
  for (auto& t : p.temperature) t = spec.initial_temperature;
  return p;
}

}  // namespace beampack
