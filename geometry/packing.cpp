#include "geometry/packing.h"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <numbers>
#include <optional>
#include <sstream>
#include <vector>

#include "geometry/cell_grid.h"
#include "geometry/error.h"
#include "geometry/input_file.h"
#include "geometry/morton.h"
#include "geometry/random.h"

namespace beampack {
namespace {

void require(bool ok, const std::string& message) {
  if (!ok) throw InputError(message);
}

// The same for checks run on every particle: the message (streams, number formatting) is built
// only when the check fails. Built every time, they took most of a 1e6-row file's read.
template <class Message>
void require_lazily(bool ok, const Message& message) {
  if (!ok) throw InputError(message());
}

void check_common(std::size_t count, double size) {
  require(count <= 100'000'000, "packing.count = " + std::to_string(count) + ": must be <= 1e8");
  require(std::isfinite(size) && size > 0, "sample.size = " + shown_number(size) + ": must be > 0");
}

// Numbers generated particles along a Morton curve: neighbours in space become neighbours in
// memory, which is what the contact search, the conduction matrix and the scene read together.
// A deterministic function of the centres, so a seed still gives one packing everywhere.
void sort_spatially(Particles& p, double size) {
  const std::size_t n = p.size();
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keys(n);
  const double scale = kMortonMax / size;
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3 q = (p.centre[i] * scale).cwiseMax(0.0).cwiseMin(kMortonMax);
    keys[i] = {morton_code(std::uint64_t(q.x()), std::uint64_t(q.y()), std::uint64_t(q.z())),
               static_cast<std::uint32_t>(i)};
  }
  std::sort(keys.begin(), keys.end());
  Particles sorted;
  sorted.reserve(n);
  for (const auto& [key, i] : keys)
    sorted.add(p.centre[i], p.radius[i], p.material[i], p.temperature[i]);
  p = std::move(sorted);
}

}  // namespace

Particles random_overlap_packing(std::size_t count, double size, double radius_ratio,
                                 std::uint64_t seed) {
  check_common(count, size);
  require(std::isfinite(radius_ratio) && radius_ratio > 0,
          "packing.radius_ratio = " + shown_number(radius_ratio) + ": must be > 0");
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
          "packing.solid_fraction = " + shown_number(solid_fraction) +
              ": must be > 0 and < 0.5 (the run file's limits); random sequential addition jams "
              "near 0.38");
  Particles p;
  if (count == 0) return p;
  PackingSpec spec;
  spec.source = "rsa", spec.count = count, spec.sample_size = size;
  spec.solid_fraction = solid_fraction;
  const double r = packing_radius(spec);
  require(2 * r < size, "packing.solid_fraction = " + shown_number(solid_fraction) +
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
        throw InputError(
            "packing.solid_fraction = " + shown_number(solid_fraction) + ": rsa placed only " +
            std::to_string(p.size()) + " of " + std::to_string(count) + " spheres (reached " +
            shown_number(solid_fraction * double(p.size()) / double(count)) + ") before " +
            std::to_string(max_failures_in_a_row) +
            " failed tries in a row; use a lower fraction (the placements stop near 0.345 at any "
            "count, short of the 0.38 where RSA jams, and lower with few spheres, where the walls "
            "leave more gaps: there, raise packing.count)");
      }
      continue;
    }
    failures = 0;
    grid.insert(c, static_cast<std::uint32_t>(p.add(c, r)));
  }
  sort_spatially(p, size);
  return p;
}

namespace {

// n, the spheres along an edge of a lattice of about `count`: the nearest whole cube root.
std::size_t lattice_side(std::size_t count) {
  return static_cast<std::size_t>(std::llround(std::cbrt(double(count))));
}

}  // namespace

std::string lattice_count_problem(std::size_t count) {
  const std::size_t n = lattice_side(count);
  if (n * n * n == count) return "";
  return "a lattice needs a cube number (n^3, e.g. " + std::to_string(n * n * n) + ")";
}

Particles lattice_packing(std::size_t count, double size, double radius_ratio) {
  check_common(count, size);
  require(std::isfinite(radius_ratio) && radius_ratio > 0,
          "packing.radius_ratio = " + shown_number(radius_ratio) + ": must be > 0");
  const std::string problem = lattice_count_problem(count);
  require(problem.empty(), "packing.count = " + std::to_string(count) + ": " + problem);
  const std::size_t n = lattice_side(count);
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

// The checks every particle of a packing passes, whichever file format (or checkpoint) gave it.
// Finite numbers can still make a sphere the physics cannot hold (found by fuzz/): a radius whose
// volume, hence mass, rounds to 0 or overflows, or a centre +- r beyond the doubles. `at()` gives
// the message's prefix, built only for a sphere that fails.
template <class Where>
void check_sphere_at(const Vec3& centre, double r, const std::array<std::size_t, 3>& centre_columns,
                     const Where& at) {
  require_lazily(centre.allFinite(), [&] { return at() + "its centre is not a finite number"; });
  require_lazily(r > 0, [&] { return at() + "radius r = " + shown_number(r) + ": must be > 0"; });
  require_lazily(r <= kMaxParticleRadius, [&] {
    return at() + "radius r = " + shown_number(r) +
           ": must be <= " + shown_number(kMaxParticleRadius) + " " + kMaxParticleRadiusWhy;
  });
  const double volume = 4.0 / 3.0 * std::numbers::pi * r * r * r;
  require_lazily(volume > 0 && std::isfinite(volume), [&] {
    return at() + "radius r = " + shown_number(r) + ": its volume " + shown_number(volume) +
           " is not a positive finite double (|r| must be at least ~1e-100)";
  });
  for (int k = 0; k < 3; ++k)
    require_lazily(std::isfinite(std::abs(centre[k]) + r), [&] {
      return at() + "centre +- radius overflows in column " + std::to_string(centre_columns[k] + 1);
    });
}

}  // namespace

void check_sphere(const Vec3& centre, double r, const std::array<std::size_t, 3>& centre_columns,
                  const std::string& where) {
  check_sphere_at(centre, r, centre_columns, [&] { return where; });
}

void check_particles(const Particles& p) {
  const std::size_t n = p.size();
  for (std::size_t size :
       {p.centre.size(), p.material.size(), p.temperature.size(), p.phase.size(), p.alive.size()})
    require_lazily(size == n, [&] {
      return "particles: the arrays differ in length (" + std::to_string(p.centre.size()) +
             " centres, " + std::to_string(n) + " radii, " + std::to_string(p.material.size()) +
             " materials, " + std::to_string(p.temperature.size()) + " temperatures, " +
             std::to_string(p.phase.size()) + " phases, " + std::to_string(p.alive.size()) +
             " live flags); Particles::add keeps them equal";
    });
  for (std::size_t i = 0; i < n; ++i) {
    const auto at = [i] { return "particle " + std::to_string(i) + ": "; };
    check_sphere_at(p.centre[i], p.radius[i], {0, 1, 2}, at);
    const double t = p.temperature[i];
    require_lazily(t > 0 && std::isfinite(t), [&] {
      return at() + "temperature " + shown_number(t) + " K: must be > 0 and finite";
    });
    require_lazily(p.alive[i] <= 1, [&] {
      return at() + "live flag " + std::to_string(p.alive[i]) + ": must be 0 or 1";
    });
  }
}

namespace {

bool is_separator(char c) {
  return c == ' ' || c == '\t' || c == ',' || c == ';';
}

// Runs of separators count as one, but two commas (or semicolons) between two values, or one
// before the first, leave an empty field, kept as an empty column (then refused by name): merged,
// "1,,2,3,0.1" read as four columns, x y z r shifted by one. Tabs and spaces are whitespace.
std::vector<std::string_view> split_columns(std::string_view line) {
  std::vector<std::string_view> cols;
  std::size_t i = 0;
  while (i < line.size()) {
    int list_separators = 0;
    for (; i < line.size() && is_separator(line[i]); ++i)
      list_separators += line[i] == ',' || line[i] == ';';
    std::size_t j = i;
    while (j < line.size() && !is_separator(line[j])) ++j;
    if (j == i) break;  // separators at the end of the line: no value shifts
    // Empty fields before this value: between two values, or before the first (",0.4,0.5,0.5"
    // would read as x = 0.4).
    const int empty = cols.empty() ? list_separators : list_separators - 1;
    for (int k = 0; k < empty; ++k) cols.push_back(line.substr(i, 0));
    cols.push_back(line.substr(i, j - i));
    i = j;
  }
  return cols;
}

// Whether the text is a number (C's notation, an optional leading '+'), into `value`; with
// `beyond` set when it is one that a double cannot hold (1e400, 1e-400).
bool parse_number(std::string_view text, double& value, bool* beyond = nullptr) {
  if (!text.empty() && text.front() == '+') {
    text.remove_prefix(1);
    if (!text.empty() && (text.front() == '+' || text.front() == '-')) return false;  // "+-1"
  }
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  const bool whole = end == text.data() + text.size();
  if (beyond) *beyond = whole && ec == std::errc::result_out_of_range;
  return ec == std::errc() && whole;
}

// A header names the columns: no column of it is a number. A data line with a typo in its first
// column is not one, and is reported instead of skipped.
bool is_header(const std::vector<std::string_view>& cols) {
  double probe;
  return std::none_of(cols.begin(), cols.end(),
                      [&](std::string_view c) { return parse_number(c, probe); });
}

std::string file_key(const std::string& path) {
  return "packing.file = \"" + path + "\": ";
}

// A file's text as a message quotes it: control bytes as \xNN (a NUL cut the message short).
std::string shown(std::string_view text) {
  std::string out;
  for (const char c : text) {
    const auto b = static_cast<unsigned char>(c);
    out += b >= 0x20 && b != 0x7F ? std::string(1, c) : escaped_byte(b);
  }
  return out;
}

// The lines of a packing file that hold something, '#' comments cut, each split into columns and
// numbered for messages. Both formats read through it, so they skip and number lines alike.
class PackingLines {
 public:
  PackingLines(std::istream& in, const std::string& path) : in_(in), path_(path) {}
  PackingLines(const PackingLines&) = delete;  // cols_ views into line_

  bool next() {
    while (read_line()) {
      ++number_;
      std::string_view text = line_;
      if (number_ == 1 && text.starts_with("\xEF\xBB\xBF")) text.remove_prefix(3);  // a UTF-8 BOM
      refuse_control_bytes(text);
      if (auto hash = text.find('#'); hash != std::string_view::npos) text = text.substr(0, hash);
      cols_ = split_columns(text);
      if (!cols_.empty()) return true;
    }
    return false;
  }
  const std::vector<std::string_view>& cols() const { return cols_; }
  std::size_t number() const { return number_; }
  std::string where() const { return path_ + ":" + std::to_string(number_) + ": "; }
  const std::string& path() const { return path_; }
  // The line a particle came from, for messages about two rows: the reader marks each row that
  // gave one, in order. Kept as runs of consecutive lines (a comment or an item starts a new
  // one), a few entries for a file of 10^7 rows.
  void mark_row() {
    if (row_runs_.empty() || number_ != last_row_line_ + 1) row_runs_.push_back({rows_, number_});
    last_row_line_ = number_;
    ++rows_;
  }
  std::size_t row_line(std::size_t row) const {
    const auto run = std::upper_bound(row_runs_.begin(), row_runs_.end(), row,
                                      [](std::size_t r, const RowRun& run) { return r < run.row; });
    return std::prev(run)->line + (row - std::prev(run)->row);
  }

 private:
  // A line of a packing file is a few dozen bytes; one of a megabyte is not text (a 20 GB sparse
  // file was read into memory as one line, until memory ran out).
  static constexpr std::size_t kMaxLine = 1 << 20;

  // A line ends at LF, CR LF (Windows) or a CR alone (classic Mac OS, whose files were read as
  // one line of many columns, or as nothing after a '#' header).
  bool read_line() {
    line_.clear();
    std::streambuf* buffer = in_.rdbuf();
    for (int c = buffer->sbumpc(); c != '\n'; c = buffer->sbumpc()) {
      if (c == std::char_traits<char>::eof()) return !line_.empty();
      if (c == '\r') {
        if (buffer->sgetc() == '\n') buffer->sbumpc();
        return true;
      }
      if (line_.size() == kMaxLine)
        throw InputError(path_ + ":" + std::to_string(number_ + 1) + ": a line longer than " +
                         std::to_string(kMaxLine) + " bytes: not a text file of particle rows");
      line_.push_back(static_cast<char>(c));
    }
    return true;
  }
  // Tabs separate columns (a carriage return ends a line); other control bytes (a NUL) mean
  // binary data, which was taken as a header line and read past without a word.
  void refuse_control_bytes(std::string_view text) const {
    for (const char c : text) {
      const auto b = static_cast<unsigned char>(c);
      if ((b < 0x20 && c != '\t') || b == 0x7F)
        throw InputError(where() + "byte " + shown(std::string_view(&c, 1)) +
                         ": not a text file of particle rows (binary data?)");
    }
  }

  std::istream& in_;
  std::string path_, line_;
  std::vector<std::string_view> cols_;
  std::size_t number_ = 0;
  struct RowRun {
    std::size_t row, line;  // the first row of the run, and its line
  };
  std::vector<RowRun> row_runs_;
  std::size_t rows_ = 0, last_row_line_ = 0;
};

// Column k of a row (numbered from 1 in messages, as editors number them) as a finite number.
double finite_column(const std::vector<std::string_view>& cols, std::size_t k,
                     const std::string& where) {
  const auto named = [&](const char* what) {
    return [&, what] {
      return where + "column " + std::to_string(k + 1) + " '" + shown(cols[k]) + "' is not " + what;
    };
  };
  double v = 0;
  bool beyond = false;
  require_lazily(parse_number(cols[k], v, &beyond) || beyond, named("a number"));
  require_lazily(!beyond, named("within the range of a double (nonzero magnitudes from 2.2e-308 "
                                "to 1.8e308)"));
  require_lazily(std::isfinite(v), named("finite"));
  return v;
}

void add_checked_sphere(Particles& p, PackingLines& lines, const Vec3& centre, double r,
                        const std::array<std::size_t, 3>& centre_columns,
                        const std::string& where) {
  check_sphere(centre, r, centre_columns, where);
  p.add(centre, r);
  lines.mark_row();
}

// Two rows with one centre are a file joined to itself or to a copy of its rows, almost always
// (the whole bed twice): spheres that hide one another from the light and conduct through a full
// cross-section, which ran without a word. Refused, naming the first row that repeats an earlier
// centre and that row's line. The centres are sorted once: O(N log N) at 10^7 rows.
void refuse_repeated_centres(const Particles& p, const PackingLines& lines) {
  const std::size_t n = p.size();
  const std::vector<Vec3>& c = p.centre;
  std::vector<std::uint32_t> order(n);  // particle ids are 32-bit throughout (tracer, heat)
  for (std::size_t i = 0; i < n; ++i) order[i] = static_cast<std::uint32_t>(i);
  std::sort(order.begin(), order.end(), [&](std::uint32_t a, std::uint32_t b) {
    for (int k = 0; k < 3; ++k)
      if (c[a][k] != c[b][k]) return c[a][k] < c[b][k];
    return a < b;  // a run of one centre is in file order
  });
  std::size_t repeats = 0, first = 0, again = n;  // again: the first row that repeats `first`
  for (std::size_t s = 0, e = 0; s < n; s = e) {
    for (e = s + 1; e < n && c[order[e]] == c[order[s]];) ++e;
    repeats += e - s - 1;
    if (e - s > 1 && order[s + 1] < again) first = order[s], again = order[s + 1];
  }
  if (repeats == 0) return;
  const Vec3& centre = c[again];
  throw InputError(
      lines.path() + ":" + std::to_string(lines.row_line(again)) + ": the centre (" +
      shown_number(centre.x()) + ", " + shown_number(centre.y()) + ", " + shown_number(centre.z()) +
      ") of line " + std::to_string(lines.row_line(first)) + " again" +
      (p.radius[again] == p.radius[first] ? ", with its radius" : "") + "; " +
      std::to_string(repeats) + " of " + std::to_string(n) +
      " rows repeat an earlier row's centre (a file joined to itself or to a copy?): two spheres "
      "at one point would hide one another from the light; remove the repeats");
}

// What a row of words may have meant to be: numbers in another notation than C's read as words.
constexpr const char* kNumberNotation = "numbers as 1.5e-4: not Fortran's 1.5D-4 or hex";

// The text between two columns of a row (their views share the line).
std::string_view between(std::string_view left, std::string_view right) {
  const char* end = left.data() + left.size();
  return {end, static_cast<std::size_t>(right.data() - end)};
}

bool all_digits(std::string_view text, bool signed_) {
  if (signed_ && !text.empty() && (text[0] == '-' || text[0] == '+')) text.remove_prefix(1);
  return !text.empty() &&
         std::all_of(text.begin(), text.end(), [](char c) { return c >= '0' && c <= '9'; });
}

// Numbers written with decimal commas (a European spreadsheet's "1,5;2,5"), each read as two
// columns: twice the columns a row needs, each pair an integer part and digits joined by a lone
// comma, the pairs apart by something else (1e-4,2e-4,... is a plain comma-separated row).
bool looks_like_decimal_commas(const std::vector<std::string_view>& cols, std::size_t need) {
  if (cols.size() != 2 * need) return false;
  for (std::size_t k = 0; k < cols.size(); k += 2) {
    if (!all_digits(cols[k], true) || !all_digits(cols[k + 1], false)) return false;
    if (between(cols[k], cols[k + 1]) != ",") return false;
    if (k + 2 < cols.size() && between(cols[k + 1], cols[k + 2]) == ",") return false;
  }
  return true;
}

// Columns x y z r (or x y z with default_radius > 0) after at most one header line; `lines`
// stands on the first line that holds something.
Particles read_plain_columns(PackingLines& lines, double default_radius) {
  const std::size_t need = default_radius > 0 ? 3 : 4;
  const std::string layout = need == 4 ? "x y z r" : "x y z";
  Particles p;
  bool seen_data = false, seen_header = false;
  do {
    const auto& cols = lines.cols();
    const std::string where = lines.where();
    if (!seen_data && is_header(cols)) {  // one header line (no column a number) before the data
      require(!seen_header, where + "no column is a number (first: '" + shown(cols[0]) +
                                "'), and one header line is allowed, before the data (" +
                                kNumberNotation + ")");
      seen_header = true;
      continue;
    }
    seen_data = true;
    require_lazily(cols.size() == need, [&] {
      return where + "expected " + std::to_string(need) + " columns (" + layout + "), found " +
             std::to_string(cols.size()) +
             (need == 4 && cols.size() == 3 ? "; for x y z rows give the radius with packing.radius"
              : need == 3 && cols.size() == 4
                  ? "; packing.radius is set, which takes x y z rows: drop it to read the radii"
              : looks_like_decimal_commas(cols, need)
                  ? "; decimal commas? A number's decimal mark is a point (1.5): 1,5 reads as two "
                    "columns"
                  : "");
    });
    double v[4] = {0, 0, 0, default_radius};
    for (std::size_t k = 0; k < need; ++k) v[k] = finite_column(cols, k, where);
    add_checked_sphere(p, lines, {v[0], v[1], v[2]}, v[3], {0, 1, 2}, where);
  } while (lines.next());
  require(p.size() > 0, file_key(lines.path()) +
                            "holds no particle (a header line only, no column of it a number; " +
                            kNumberNotation + ")");
  return p;
}

// --- LAMMPS / LIGGGHTS text dumps (`dump ID group custom N file id type x y z radius`) ---

// Where the centre and the radius of a particle stand in a dump's ATOMS rows.
struct AtomColumns {
  std::size_t count = 0;  // columns a row must have
  std::array<std::size_t, 3> centre{};
  std::optional<std::size_t> radius;  // none: every sphere has the default radius
  double radius_per_value = 1.0;      // 0.5 when the column is a diameter
};

std::string joined(const std::vector<std::string_view>& words) {
  std::string s;
  for (auto w : words) {
    if (!s.empty()) s += ' ';
    s += shown(w);
  }
  return s;
}

// Reads `ITEM: ATOMS <names>`: x y z, else the unwrapped xu yu zu; radius, else diameter, else
// the default radius. Scaled coordinates are refused: unscaling them needs the box, and a
// triclinic box's tilt, which beampack would then have to get right for every dump style.
AtomColumns atom_columns(const std::vector<std::string_view>& names, double default_radius,
                         const std::string& where) {
  auto column = [&](std::string_view name) -> std::optional<std::size_t> {
    const auto it = std::find(names.begin(), names.end(), name);
    if (it == names.end()) return std::nullopt;
    return std::size_t(it - names.begin());
  };
  const std::string found = "ITEM: ATOMS names " + joined(names);
  AtomColumns a;
  a.count = names.size();
  std::optional<std::size_t> x, y, z;
  for (const auto& [cx, cy, cz] : {std::array{"x", "y", "z"}, std::array{"xu", "yu", "zu"}}) {
    x = column(cx), y = column(cy), z = column(cz);
    if (x && y && z) break;
  }
  if (!(x && y && z)) {
    const bool scaled = column("xs") || column("ys") || column("zs") || column("xsu") ||
                        column("ysu") || column("zsu");
    throw InputError(where + found +
                     (scaled ? ": scaled coordinates (xs ys zs, xsu ysu zsu) are not read; "
                               "dump x y z (or xu yu zu) instead"
                             : ": no centre columns; a dump needs x y z (or xu yu zu)"));
  }
  a.centre = {*x, *y, *z};
  // Two radii for one sphere: which to use is the user's to say (a plain x y z r file refuses
  // packing.radius the same way).
  require(!(default_radius > 0 && (column("radius") || column("diameter"))),
          where + found + ": the dump gives radii, and packing.radius gives one too; drop one");
  if ((a.radius = column("radius"))) return a;
  if ((a.radius = column("diameter"))) {
    a.radius_per_value = 0.5;
    return a;
  }
  require(default_radius > 0, where + found +
                                  ": no radius or diameter column; dump radius, "
                                  "or give the spheres' radius with packing.radius");
  return a;
}

// A dump's ATOMS row as a sphere, through the same checks as a plain file's rows.
void add_atom_row(Particles& p, PackingLines& lines, const AtomColumns& a, double default_radius,
                  const std::vector<std::string_view>& cols, const std::string& where,
                  std::size_t header_line) {
  require(cols.size() == a.count,
          where + "expected " + std::to_string(a.count) + " columns (as ITEM: ATOMS on line " +
              std::to_string(header_line) + " names), found " + std::to_string(cols.size()));
  Vec3 centre;
  for (int k = 0; k < 3; ++k) centre[k] = finite_column(cols, a.centre[k], where);
  const double r =
      a.radius ? a.radius_per_value * finite_column(cols, *a.radius, where) : default_radius;
  add_checked_sphere(p, lines, centre, r, a.centre, where);
}

bool is_item_line(const std::vector<std::string_view>& cols) {
  return cols[0].starts_with("ITEM:");
}

// The words of an item line after "ITEM:", one space apart ("BOX BOUNDS xy xz yz pp pp pp").
std::string item_text(const std::vector<std::string_view>& cols) {
  std::vector<std::string_view> words(cols.begin() + 1, cols.end());
  if (cols[0].size() > 5) words.insert(words.begin(), cols[0].substr(5));
  return joined(words);
}

// The items of a LAMMPS text dump; UNITS and TIME appear with dump_modify units / time yes.
constexpr std::array<std::string_view, 6> kDumpItems = {"TIMESTEP", "NUMBER OF ATOMS", "BOX BOUNDS",
                                                        "ATOMS",    "UNITS",           "TIME"};

std::string_view dump_item(std::string_view text) {
  for (std::string_view name : kDumpItems)
    if (text.starts_with(name) && (text.size() == name.size() || text[name.size()] == ' '))
      return name;
  return {};
}

std::uint64_t whole_number(const std::vector<std::string_view>& cols, std::string_view item,
                           const std::string& where) {
  std::uint64_t n = 0;
  const std::string_view t = cols[0];
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), n);
  require(cols.size() == 1 && ec == std::errc() && end == t.data() + t.size(),
          where + "ITEM: " + std::string(item) + " '" + joined(cols) +
              "': must be one whole number >= 0");
  return n;
}

// Reads one snapshot item by item: an "ITEM: NAME ..." line opens an item, the lines up to the
// next one are its rows, and each item's row count is checked when the next one opens.
class DumpReader {
 public:
  DumpReader(PackingLines& lines, double default_radius)
      : lines_(lines), default_radius_(default_radius) {}

  Particles read() {
    do {
      if (is_item_line(lines_.cols())) {
        close_item();
        open_item();
      } else {
        read_row();
      }
    } while (lines_.next());
    close_item();
    const std::string key = file_key(lines_.path());
    require(first_line_.count("ATOMS"), key + "a dump without ITEM: ATOMS holds no particle");
    require(atom_count_ > 0, key + "ITEM: NUMBER OF ATOMS is 0: the dump holds no particle");
    return std::move(particles_);
  }

 private:
  void open_item() {
    const std::string where = lines_.where(), text = item_text(lines_.cols());
    const std::string_view name = dump_item(text);
    require(!name.empty(), where + "ITEM: " + text + ": not an item of a LAMMPS text dump (" +
                               "TIMESTEP, NUMBER OF ATOMS, BOX BOUNDS, ATOMS, UNITS, TIME)");
    // A second TIMESTEP, or a second TIME (dump_modify time yes writes it before TIMESTEP).
    if ((name == "TIMESTEP" || name == "TIME") && first_line_.count(name))
      refuse_snapshots(where, name == "TIMESTEP" ? 2 : 1);
    if (const auto first = first_line_.find(name); first != first_line_.end())
      throw InputError(where + "a second ITEM: " + std::string(name) + " (the first is on line " +
                       std::to_string(first->second) + ")");
    first_line_[name] = lines_.number();
    item_ = name;
    rows_ = 0;
    if (name == "BOX BOUNDS")  // lo hi; a tilt factor (triclinic); a vector and an origin (general)
      box_columns_ = text.find(" abc origin") != std::string::npos ? 4
                     : text.find(" xy") != std::string::npos       ? 3
                                                                   : 2;
    if (name == "ATOMS") {
      require(first_line_.count("NUMBER OF ATOMS"),
              where + "ITEM: ATOMS before ITEM: NUMBER OF ATOMS; a dump gives the count first");
      atoms_ =
          atom_columns(split_columns(std::string_view(text).substr(5)), default_radius_, where);
    }
  }

  void read_row() {
    const auto& cols = lines_.cols();
    const std::string where = lines_.where();
    ++rows_;
    if (item_ == "ATOMS") {
      add_atom_row(particles_, lines_, atoms_, default_radius_, cols, where, first_line_["ATOMS"]);
    } else if (item_ == "NUMBER OF ATOMS" || item_ == "TIMESTEP") {
      const std::uint64_t n = whole_number(cols, item_, where);
      if (item_ == "NUMBER OF ATOMS") atom_count_ = n;
    } else if (item_ == "BOX BOUNDS") {
      require(cols.size() == box_columns_,
              where + "expected " + std::to_string(box_columns_) + " columns (" +
                  (box_columns_ == 4   ? "a vector and an origin"
                   : box_columns_ == 3 ? "lo hi tilt"
                                       : "lo hi") +
                  ", as ITEM: BOX BOUNDS names), found " + std::to_string(cols.size()));
      for (std::size_t k = 0; k < cols.size(); ++k) finite_column(cols, k, where);
    }  // UNITS and TIME: a name and a time the simulation does not use
  }

  // Each item has the rows it announces; a truncated or hand-edited dump stops here.
  void close_item() {
    if (item_.empty()) return;
    const std::size_t line = first_line_[item_];
    const std::string where = lines_.path() + ":" + std::to_string(line) + ": ";
    if (item_ == "ATOMS") {
      require(rows_ == atom_count_, where + "ITEM: ATOMS is followed by " + std::to_string(rows_) +
                                        " rows; ITEM: NUMBER OF ATOMS (line " +
                                        std::to_string(first_line_["NUMBER OF ATOMS"]) + ") says " +
                                        std::to_string(atom_count_));
      return;
    }
    const std::size_t need = item_ == "BOX BOUNDS" ? 3 : 1;
    require(rows_ == need, where + "ITEM: " + std::string(item_) + " is followed by " +
                               std::to_string(rows_) + " lines; it needs " + std::to_string(need));
  }

  // Which snapshot to simulate is the user's choice, so a trajectory is refused, never cut.
  [[noreturn]] void refuse_snapshots(const std::string& where, std::size_t snapshots) {
    while (lines_.next())
      if (is_item_line(lines_.cols()) && dump_item(item_text(lines_.cols())) == "TIMESTEP")
        ++snapshots;
    throw InputError(where + "a second snapshot: the dump holds " + std::to_string(snapshots) +
                     " snapshots; keep one (the one to simulate) in the file, e.g. with "
                     "LAMMPS write_dump or by cutting the file at its ITEM: TIMESTEP lines");
  }

  PackingLines& lines_;
  double default_radius_;
  Particles particles_;
  std::string_view item_;  // the item being read, one of kDumpItems; empty before the first
  std::size_t rows_ = 0;
  std::map<std::string_view, std::size_t> first_line_;  // the line each item opens on
  std::uint64_t atom_count_ = 0;
  std::size_t box_columns_ = 2;  // lo hi, and a tilt factor in a triclinic box
  AtomColumns atoms_;
};

}  // namespace

Particles read_packing_file(const std::string& path, double default_radius) {
  require(!unsafe_input_file(path),
          file_key(path) + "not a regular file (a directory, FIFO or device)");
  std::ifstream in(path);
  require(in.good(), file_key(path) + "cannot open for reading");
  PackingLines lines(in, path);
  // An empty bed is allowed when asked for (packing.count = 0), not from a file that lost its data.
  require(lines.next(), file_key(path) + "holds no particle (no data line)");
  Particles p = is_item_line(lines.cols()) ? DumpReader(lines, default_radius).read()
                                           : read_plain_columns(lines, default_radius);
  require(!in.bad(), file_key(path) + "read error");
  refuse_repeated_centres(p, lines);
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

double median_radius(const Particles& particles) {
  std::vector<double> r = particles.radius;
  if (r.empty()) return 0;
  const auto mid = r.begin() + std::ptrdiff_t(r.size() / 2);
  std::nth_element(r.begin(), mid, r.end());
  if (r.size() % 2) return *mid;
  return 0.5 * (*mid + *std::max_element(r.begin(), mid));
}

double packing_radius(const PackingSpec& s) {
  const double n = double(std::max<std::size_t>(s.count, 1));
  if (s.source == "rsa")
    return s.sample_size * std::cbrt(3.0 * s.solid_fraction / (4.0 * std::numbers::pi * n));
  if (s.source == "file") return median_radius(read_packing_file(s.file, s.file_radius));
  return s.radius_ratio * s.sample_size / std::cbrt(n);
}

std::string radius_setting(const PackingSpec& s) {
  if (s.source == "rsa") return "`packing.solid_fraction` = " + shown_number(s.solid_fraction);
  if (s.source != "file") return "`packing.radius_ratio` = " + shown_number(s.radius_ratio);
  return s.file_radius > 0 ? "`packing.radius` = " + shown_number(s.file_radius) : "";
}

Particles make_packing(const PackingSpec& spec) {
  Particles p;
  if (spec.source == "random-overlap")
    p = random_overlap_packing(spec.count, spec.sample_size, spec.radius_ratio, spec.seed);
  else if (spec.source == "rsa")
    p = rsa_packing(spec.count, spec.sample_size, spec.solid_fraction, spec.seed);
  else if (spec.source == "lattice")
    p = lattice_packing(spec.count, spec.sample_size, spec.radius_ratio);
  else if (spec.source == "file") p = read_packing_file(spec.file, spec.file_radius);
  else
    throw InputError("packing.source = \"" + spec.source +
                     "\": must be one of random-overlap, rsa, lattice, file");
  for (auto& t : p.temperature) t = spec.initial_temperature;
  return p;
}

}  // namespace beampack
