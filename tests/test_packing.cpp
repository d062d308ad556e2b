// Packings: counts, radii, bounds, seeds, non-overlap, and the x y z r and LAMMPS dump file formats
// with their errors.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/expect_error.h"
#include "tests/test_dirs.h"

using namespace beampack;
namespace fs = std::filesystem;

namespace {

bool same_packing(const Particles& a, const Particles& b) {
  return a.centre == b.centre && a.radius == b.radius;
}

std::string temp_file(const std::string& name, const std::string& text) {
  const fs::path path = beampack::testing::process_dir() / name;
  std::ofstream(path) << text;
  return path.string();
}

// The InputError message of reading `text`, or testing::kAccepted when it parses.
std::string read_error(const std::string& name, const std::string& text, double radius = 0) {
  return beampack::testing::error_message<InputError>(
      [&] { read_packing_file(temp_file(name, text), radius); });
}

}  // namespace

TEST(Packing, RandomOverlapFollowsThePaper) {
  const double D = 1e-3, L = 0.325;
  const Particles p = random_overlap_packing(1000, D, L, 1);
  ASSERT_EQ(p.size(), 1000u);
  const double R = L * std::cbrt(D * D * D / 1000);  // R = L (D^3/N)^(1/3)
  for (std::size_t i = 0; i < p.size(); ++i) {
    ASSERT_DOUBLE_EQ(p.radius[i], R);
    ASSERT_TRUE((p.centre[i].array() >= 0).all() && (p.centre[i].array() <= D).all());
    ASSERT_EQ(p.phase[i], Phase::solid);
    ASSERT_TRUE(p.alive[i]);
  }
  // Uniform centres: the mean is near D/2 (standard error D/sqrt(12 N) ~ 9e-6).
  Vec3 mean = Vec3::Zero();
  for (const Vec3& c : p.centre) mean += c / 1000.0;
  EXPECT_NEAR(mean.x(), D / 2, 5 * D / std::sqrt(12.0 * 1000));
}

TEST(Packing, SameSeedSamePackingOtherSeedOther) {
  EXPECT_TRUE(
      same_packing(random_overlap_packing(500, 1, 0.3, 7), random_overlap_packing(500, 1, 0.3, 7)));
  EXPECT_FALSE(
      same_packing(random_overlap_packing(500, 1, 0.3, 7), random_overlap_packing(500, 1, 0.3, 8)));
  EXPECT_TRUE(same_packing(rsa_packing(300, 1, 0.2, 3), rsa_packing(300, 1, 0.2, 3)));
}

TEST(Packing, SeedGivesTheSameNumbersOnEveryMachine) {
  // Pinned values of xoshiro256** seeded by splitmix64, after the Morton numbering: a change of
  // generator, of the order of draws or of the numbering, or a platform-dependent distribution,
  // shows up here.
  const Particles p = random_overlap_packing(2, 1.0, 0.3, 1);
  EXPECT_EQ(p.centre[0].x(), 0x1.90b871ef099a8p-2);
  EXPECT_EQ(p.centre[1].z(), 0x1.25f12eac10548p-1);
}

TEST(Packing, RsaHasNoOverlapsAndReachesTheFraction) {
  const double D = 1.0, phi = 0.3;
  const Particles p = rsa_packing(2000, D, phi, 11);
  ASSERT_EQ(p.size(), 2000u);
  EXPECT_TRUE(find_contacts(p).empty());
  double volume = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    volume += p.volume(i);
    const double r = p.radius[i];
    ASSERT_TRUE((p.centre[i].array() >= r).all() && (p.centre[i].array() <= D - r).all());
  }
  EXPECT_NEAR(volume / (D * D * D), phi, 1e-12);
}

TEST(Packing, RsaBeyondJammingIsAClearErrorInBoundedWork) {
  beampack::testing::expect_error<InputError>([] { rsa_packing(3000, 1.0, 0.45, 1); },
                                              "packing.solid_fraction = 0.45", "jams");
  EXPECT_THROW(rsa_packing(10, 1.0, 0.7, 1), InputError);
  // Refused at once, not after the placements: the limit is open.
  beampack::testing::expect_error<InputError>([] { rsa_packing(10, 1.0, 0.5, 1); },
                                              "must be > 0 and < 0.5");
  // Few spheres jam sooner: 200 at 0.3 do not fit (2000 do, above), and the error says that more
  // spheres help, not only a lower fraction.
  beampack::testing::expect_error<InputError>([] { rsa_packing(200, 1.0, 0.3, 7); },
                                              "lower with few spheres", "raise packing.count");
}

TEST(Packing, LatticeIsSimpleCubic) {
  const Particles p = lattice_packing(27, 3.0, 0.5);
  ASSERT_EQ(p.size(), 27u);
  EXPECT_EQ(p.centre[0], Vec3(0.5, 0.5, 0.5));
  EXPECT_EQ(p.centre[26], Vec3(2.5, 2.5, 2.5));
  EXPECT_DOUBLE_EQ(p.radius[0], 0.5);
  EXPECT_TRUE(find_contacts(p).empty());  // radius a/2: neighbours just touch, no overlap
  EXPECT_EQ(find_contacts(lattice_packing(27, 3.0, 0.6)).size(), 54u);  // 3 * 3 * 3 * 2 bonds
  EXPECT_THROW(lattice_packing(26, 3.0, 0.5), InputError);
}

TEST(Packing, BadParametersNameTheKey) {
  const auto message = beampack::testing::error_message<InputError>;
  EXPECT_CONTAINS(message([] { random_overlap_packing(10, -1, 0.3, 1); }), "sample.size");
  EXPECT_CONTAINS(message([] { random_overlap_packing(10, 1, NAN, 1); }), "packing.radius_ratio");
  PackingSpec spec;
  spec.source = "hexagonal";
  EXPECT_CONTAINS(message([&] { make_packing(spec); }), "packing.source");
}

TEST(PackingFile, RoundTripIsExact) {
  const Particles p = random_overlap_packing(1000, 1e-3, 0.325, 5);
  const std::string path = (beampack::testing::process_dir() / "roundtrip.xyzr").string();
  write_packing_file(path, p);
  EXPECT_TRUE(same_packing(read_packing_file(path), p));
}

TEST(PackingFile, HeaderCommentsAndBlankLinesAreAllowed) {
  const Particles p = read_packing_file(temp_file(
      "header", "x y z r\n# a comment\n\n1 2 3 0.5  # trailing\n4,5,6,0.25\n7;8;9;0.125\r\n"));
  ASSERT_EQ(p.size(), 3u);
  EXPECT_EQ(p.centre[1], Vec3(4, 5, 6));
  EXPECT_EQ(p.radius[1], 0.25);
  EXPECT_EQ(p.centre[2], Vec3(7, 8, 9));  // semicolons (spreadsheets with a decimal comma)
  EXPECT_EQ(p.radius[2], 0.125);
}

// A pipe whose writer runs, as a shell's process substitution gives one (/dev/fd/N), is read; a
// named FIFO or a device is refused unread (tests/test_cli.cpp).
TEST(PackingFile, APipeFromProcessSubstitutionIsRead) {
  int fds[2];
  ASSERT_EQ(pipe(fds), 0);
  const std::string text = "0 0 0 1\n2 0 0 0.5\n";
  ASSERT_EQ(write(fds[1], text.data(), text.size()), static_cast<ssize_t>(text.size()));
  close(fds[1]);
  const Particles p = read_packing_file("/dev/fd/" + std::to_string(fds[0]));
  close(fds[0]);
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p.radius[1], 0.5);
}

// Lines end at LF, CR LF or a CR alone (classic Mac OS). A CR-only file was read as one line:
// "expected 4 columns, found 12", or no particle at all after a '#' header.
TEST(PackingFile, LinesEndingInACarriageReturnAloneAreRead) {
  for (const std::string header : {"# x y z r\r", "x y z r\r", ""}) {
    const Particles p = read_packing_file(temp_file("mac", header + "1 2 3 0.5\r4 5 6 0.25\r"));
    ASSERT_EQ(p.size(), 2u) << header;
    EXPECT_EQ(p.centre[1], Vec3(4, 5, 6));
    EXPECT_EQ(p.radius[1], 0.25);
  }
  // Every kind in one file, and errors on the line an editor shows.
  EXPECT_EQ(
      read_packing_file(temp_file("mixed", "1 2 3 1\r\n4 5 6 1\r7 8 9 1\n\r\r\n1 1 1 1")).size(),
      4u);
  EXPECT_CONTAINS(read_error("mac_cols", "# x y z r\r1 2 3 1\r\r1 2 3\r"),
                  ":4: expected 4 columns (x y z r), found 3");
  EXPECT_CONTAINS(read_error("crlf_cols", "1 2 3 1\r\n\r\n1 2 3\r\n"),
                  ":3: expected 4 columns (x y z r), found 3");
  const std::string dump =
      "ITEM: TIMESTEP\r0\rITEM: NUMBER OF ATOMS\r1\rITEM: BOX BOUNDS pp pp pp\r0 1\r0 1\r0 1\r"
      "ITEM: ATOMS id x y z radius\r1 0.1 0.2 0.3 0.01\r";
  EXPECT_EQ(read_packing_file(temp_file("mac.dump", dump)).radius, std::vector<double>{0.01});
}

// Commas, semicolons, tabs and spaces separate columns, alone or together ("1, 2").
TEST(PackingFile, ColumnsSeparatedByCommasOrSpacesAreRead) {
  const Particles p = read_packing_file(
      temp_file("bed.csv", "x,y,z,r\n1,2,3,0.1\n4, 5 ,6,0.2\n7;8;9;0.3,\n\t10\t11 12 0.4\n"));
  ASSERT_EQ(p.size(), 4u);
  EXPECT_EQ(p.centre[1], Vec3(4, 5, 6));
  EXPECT_EQ(p.radius[2], 0.3);
  EXPECT_EQ(p.centre[3], Vec3(10, 11, 12));
}

TEST(PackingFile, EachErrorNamesItsLine) {
  EXPECT_CONTAINS(read_error("cols", "1 2 3 1\n1 2 3\n"), ":2: expected 4 columns");
  // An x y z file read without packing.radius: the message says where the radius goes.
  EXPECT_CONTAINS(read_error("xyz", "1 2 3\n"),
                  ":1: expected 4 columns (x y z r), found 3; for x y z rows give "
                  "the radius with packing.radius");
  // And an x y z r file read with packing.radius: the message says the key is what asks for three.
  EXPECT_CONTAINS(read_error("xyzr", "1 2 3 1\n", 0.5),
                  ":1: expected 3 columns (x y z), found 4; packing.radius is set, which "
                  "takes x y z rows");
  // A number a double cannot hold is said to be one, not "not a number".
  EXPECT_CONTAINS(read_error("beyond_double", "1 2 1e400 1\n"),
                  ":1: column 3 '1e400' is not within the range of a double");
  EXPECT_CONTAINS(read_error("below_double", "1 2 3 1e-400\n"),
                  ":1: column 4 '1e-400' is not within the range of a double");
  EXPECT_CONTAINS(read_error("nan_text", "# c\n1 2 abc 1\n"), ":2: column 3 'abc' is not a number");
  EXPECT_CONTAINS(read_error("neg", "1 2 3 1\n\n1 2 3 -1\n"), ":3: radius r = -1: must be > 0");
  EXPECT_CONTAINS(read_error("zero", "1 2 3 0\n"), ":1: radius r = 0");
  // Far beyond any sample the ray scene's float bounds lose the sphere (at 1e20 m nothing was
  // hit, without a word): the limit packing.radius has, for a file's own radii too.
  EXPECT_CONTAINS(read_error("huge", "1 2 3 1e6\n1 2 3 1e20\n"),
                  ":2: radius r = 1e+20: must be <= 1e+06 m");
  EXPECT_CONTAINS(read_error("nan", "1 nan 3 1\n"), ":1: column 2 'nan' is not finite");
  EXPECT_CONTAINS(read_error("inf", "1 2 3 1\ninf 2 3 1\n"), ":2: column 1 'inf' is not finite");
  EXPECT_CONTAINS(read_error("extra", "1 2 3 1 5\n"), ":1: expected 4 columns");
  // An empty field between commas is a column, not nothing: merged with its neighbours it shifted
  // x y z r by one ("1,,2,3,0.1" read as x = 1, y = 2, z = 3, r = 0.1).
  EXPECT_CONTAINS(read_error("empty_field", "1,,2,3,0.1\n"),
                  ":1: expected 4 columns (x y z r), found 5");
  EXPECT_CONTAINS(read_error("empty_field_4", "1;;2;0.1\n"), ":1: column 2 '' is not a number");
  EXPECT_CONTAINS(read_error("leading_empty", "x,y,z\n,0.4,0.5,0.5\n", 0.05),
                  ":2: expected 3 columns (x y z), found 4");
  // Decimal commas (a European spreadsheet's export) split each number in two: said so where
  // each pair is an integer part and digits joined by a lone comma, the pairs apart by another
  // separator.
  EXPECT_CONTAINS(read_error("decimal_commas", "1,5;2,5;3,5;0,1\n"),
                  ":1: expected 4 columns (x y z r), found 8; decimal commas? A number's decimal "
                  "mark is a point (1.5): 1,5 reads as two columns");
  EXPECT_CONTAINS(read_error("decimal_commas_xyz", "x y z\n0,4 0,5 0,5\n", 0.05),
                  ":2: expected 3 columns (x y z), found 6; decimal commas?");
  EXPECT_EQ(read_error("eight_columns", "1 2 3 1 5 6 7 8\n").find("decimal"), std::string::npos);
  // A plain comma-separated row of eight numbers is not one of decimal commas.
  EXPECT_EQ(read_error("eight_csv", "1e-4,2e-4,3e-4,5e-5,0,0,0,1\n").find("decimal"),
            std::string::npos);
  EXPECT_EQ(read_error("eight_int_csv", "1,5,2,5,3,5,0,1\n").find("decimal"), std::string::npos);
  EXPECT_CONTAINS(read_error("plus_minus", "+-1 2 3 1\n"), ":1: column 1 '+-1' is not a number");
  // A NUL or other control byte is binary data, refused and shown (not left to end the message);
  // a header line of them was taken as a header and read past.
  EXPECT_CONTAINS(read_error("nul", std::string("1 2 0.3\0x 1\n", 12)),
                  ":1: byte \\x00: not a text file of particle rows");
  EXPECT_CONTAINS(read_error("nul_header", std::string(100, '\0') + "\n1 2 3 1\n"),
                  ":1: byte \\x00: not a text file");
  // No line of a text file of rows is a megabyte long: reading stops there (a 20 GB sparse file
  // was read as one line until memory ran out).
  EXPECT_CONTAINS(read_error("long_line", "x y z r\n" + std::string(2 << 20, '1') + "\n"),
                  ":2: a line longer than 1048576 bytes");
  EXPECT_CONTAINS(read_error("header_late", "1 2 3 1\nx y z r\n"),
                  ":2: column 1 'x' is not a number");
  // Before the data: one header, and a typo in the first data line is an error, not a header.
  EXPECT_CONTAINS(read_error("two_headers", "x y z r\nid x y z\n1 2 3 1\n"),
                  ":2: no column is a number (first: 'id'), and one header line is allowed");
  // Numbers in another notation than C's read as words: the message says which notation reads.
  EXPECT_CONTAINS(read_error("fortran", "5.0D-4 5.0D-4 5.0D-4 1.0D-4\n"),
                  "a header line only, no column of it a number; numbers as 1.5e-4: not "
                  "Fortran's 1.5D-4");
  EXPECT_CONTAINS(read_error("typo_first", "1.0e-3x 2 3 1\n4 5 6 1\n"),
                  ":1: column 1 '1.0e-3x' is not a number");
  // A file without data is refused (an empty bed is asked for with packing.count = 0).
  EXPECT_CONTAINS(read_error("empty", ""), "holds no particle (no data line)");
  EXPECT_CONTAINS(read_error("comments", "# x y z r\n\n# nothing\n"), "holds no particle");
  EXPECT_CONTAINS(read_error("header_only", "x y z r\n"), "holds no particle (a header line only");
  beampack::testing::expect_error<InputError>(
      [] { read_packing_file("/nonexistent/beampack.xyz"); }, "packing.file");
}

TEST(PackingFile, ReadsTheDemBedWithItsRadius) {
  const std::string path = std::string(BEAMPACK_DATA_DIR) + "/dem_bed_28367_r0.01.xyz";
  if (!fs::exists(path)) GTEST_SKIP() << "shared data not present at " << path;
  const Particles p = read_packing_file(path, 0.01);
  ASSERT_EQ(p.size(), 28367u);
  // Centres in x, y within [-0.5, 0.5], z in [0, 0.2]; the lowest spheres press slightly into the
  // floor (centre z ~ 0.0093 < r), as soft-sphere DEM leaves them.
  Box centres;
  for (const Vec3& c : p.centre) centres.grow(c, 0.0);
  EXPECT_GT(centres.lower.z(), 0.009);
  EXPECT_LT(centres.lower.z(), 0.01);
  EXPECT_LE(centres.upper.z(), 0.2);
  EXPECT_GE(centres.lower.x(), -0.5);
  EXPECT_LE(centres.upper.x(), 0.5);
  // Soft-sphere DEM leaves slight overlaps: closest centres 0.0193 m apart, radius 0.01 m.
  const auto contacts = find_contacts(p);
  EXPECT_GT(contacts.size(), p.size());
  // Without a default radius the three-column file is an error on line 1.
  EXPECT_CONTAINS(read_error("dem3", "0.1 0.2 0.3\n"), ":1: expected 4 columns (x y z r), found 3");
}

namespace {

// A one-snapshot LAMMPS text dump (`dump ... custom ...`) whose ITEM: ATOMS line names `columns`;
// NUMBER OF ATOMS is the row count unless `count` says otherwise.
std::string lammps_dump(const std::string& columns, const std::vector<std::string>& rows,
                        long count = -1, const std::string& timestep = "1000",
                        const std::string& box = "BOX BOUNDS pp pp fm\n-0.5 0.5\n-0.5 0.5\n0 0.2") {
  std::string text = "ITEM: TIMESTEP\n" + timestep + "\nITEM: NUMBER OF ATOMS\n" +
                     std::to_string(count < 0 ? long(rows.size()) : count) + "\nITEM: " + box +
                     "\nITEM: ATOMS " + columns + "\n";
  for (const auto& row : rows) text += row + "\n";
  return text;
}

// The line of `text` (from 1) that starts with `start`, as it appears in error messages.
std::string line_of(const std::string& text, const std::string& start) {
  std::size_t line = 1;
  for (std::size_t at = 0; at < text.size(); at = text.find('\n', at) + 1, ++line)
    if (text.compare(at, start.size(), start) == 0) return ":" + std::to_string(line) + ": ";
  return "(no line starting '" + start + "')";
}

}  // namespace

// Two rows with one centre are almost always a file joined to itself or to a copy: they ran as
// coincident spheres without a word. Refused, naming the first row that repeats and the row it
// repeats, by the lines an editor shows (comments and blank lines counted).
TEST(PackingFile, RepeatedCentresAreRefusedNamingBothLines) {
  EXPECT_CONTAINS(read_error("joined",
                             "# bed\n1 2 3 0.5\n4 5 6 0.5\n\n# bed again\n1 2 3 0.5\n"
                             "4 5 6 0.5\n"),
                  ":6: the centre (1, 2, 3) of line 2 again, with its radius; 2 of 4 rows repeat "
                  "an earlier row's centre (a file joined to itself or to a copy?)");
  const std::string other_radius = read_error("other_radius", "1 2 3 0.5\n7 8 9 1\n1 2 3 0.25\n");
  EXPECT_CONTAINS(other_radius, ":3: the centre (1, 2, 3) of line 1 again; 1 of 3 rows");
  EXPECT_NOT_CONTAINS(other_radius, "with its radius");
  // The first repeat in the file's order, whichever centre sorts first.
  EXPECT_CONTAINS(read_error("order", "1 1 1 1\n9 9 9 1\n9 9 9 1\n1 1 1 1\n"),
                  ":3: the centre (9, 9, 9) of line 2 again");
  EXPECT_CONTAINS(read_error("three_copies", "1 1 1 1\n2 2 2 1\n1 1 1 1\n1 1 1 1\n"),
                  ":3: the centre (1, 1, 1) of line 1 again, with its radius; 2 of 4 rows");
  EXPECT_CONTAINS(read_error("signed_zero", "0 0 0 1\n-0 0 0 1\n"), ":2: the centre (-0, 0, 0)");
  // A dump's rows too, by their lines in the dump (its rows start on line 10).
  const std::string dump =
      lammps_dump("id type x y z radius",
                  {"1 1 0.1 0.2 0.3 0.01", "2 1 0.4 0.2 0.3 0.01", "3 1 0.1 0.2 0.3 0.01"});
  EXPECT_CONTAINS(read_error("dump_repeat", dump),
                  ":12: the centre (0.1, 0.2, 0.3) of line 10 again");
  // Centres one bit apart are two spheres.
  EXPECT_EQ(read_packing_file(temp_file("one_bit", "1 2 3 1\n1 2 3.0000000000000004 1\n")).size(),
            2u);
}

TEST(PackingDump, RadiusColumnIsReadExactly) {
  const Particles p = read_packing_file(temp_file(
      "dump_radius",
      lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.05 0.01", "2 1 -0.3 0.4 0.125 0.0125"})));
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p.centre[0], Vec3(0.1, 0.2, 0.05));
  EXPECT_EQ(p.radius[0], 0.01);
  EXPECT_EQ(p.centre[1], Vec3(-0.3, 0.4, 0.125));
  EXPECT_EQ(p.radius[1], 0.0125);
}

TEST(PackingDump, DiameterColumnIsHalved) {
  const Particles p = read_packing_file(
      temp_file("dump_diameter", lammps_dump("id type x y z diameter", {"1 1 0.1 0.2 0.3 0.02"})));
  ASSERT_EQ(p.size(), 1u);
  EXPECT_EQ(p.radius[0], 0.01);
  EXPECT_EQ(p.centre[0], Vec3(0.1, 0.2, 0.3));
}

TEST(PackingDump, UnwrappedCoordinatesAreUsedAndWrappedOnesPreferred) {
  const Particles u = read_packing_file(
      temp_file("dump_xu", lammps_dump("id type xu yu zu radius", {"1 1 1.5 -2.5 0.1 0.01"})));
  ASSERT_EQ(u.size(), 1u);
  EXPECT_EQ(u.centre[0], Vec3(1.5, -2.5, 0.1));
  const Particles both = read_packing_file(
      temp_file("dump_x_and_xu",
                lammps_dump("id xu yu zu x y z radius", {"1 1.5 -2.5 0.1 0.5 0.25 0.1 0.01"})));
  EXPECT_EQ(both.centre[0], Vec3(0.5, 0.25, 0.1));
}

TEST(PackingDump, ColumnsInAnyOrderAndExtraColumns) {
  const Particles p = read_packing_file(temp_file(
      "dump_order", lammps_dump("id type vx x radius y z",
                                {"7 2 -9.5 0.1 0.01 0.2 0.3", "8 2 4.0 0.4 0.02 0.5 0.6"})));
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p.centre[0], Vec3(0.1, 0.2, 0.3));
  EXPECT_EQ(p.radius[0], 0.01);
  EXPECT_EQ(p.centre[1], Vec3(0.4, 0.5, 0.6));
  EXPECT_EQ(p.radius[1], 0.02);
}

TEST(PackingDump, TriclinicBoxAndOptionalItemsAreAccepted) {
  const std::string text =
      "ITEM: UNITS\nsi\nITEM: TIME\n0.5\n" +
      lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.05 0.01"}, -1, "0",
                  "BOX BOUNDS xy xz yz pp pp pp\n-0.5 0.5 0.1\n-0.5 0.5 0\n0 0.2 0");
  EXPECT_EQ(read_packing_file(temp_file("dump_triclinic", text)).centre[0], Vec3(0.1, 0.2, 0.05));
  std::string orthogonal_bounds = text;
  orthogonal_bounds.replace(orthogonal_bounds.find("-0.5 0.5 0.1"), 12, "-0.5 0.5");
  EXPECT_CONTAINS(read_error("dump_tilt_missing", orthogonal_bounds),
                  line_of(orthogonal_bounds, "-0.5 0.5\n") + "expected 3 columns (lo hi tilt");
}

TEST(PackingDump, SeveralSnapshotsAreRefusedWithTheirCount) {
  const std::string one = lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.05 0.01"});
  const std::string three =
      one + lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.04 0.01"}, -1, "2000") +
      lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.03 0.01"}, -1, "3000");
  const std::string m = read_error("dump_three", three);
  EXPECT_CONTAINS(m, ":11: a second snapshot");
  EXPECT_CONTAINS(m, "holds 3 snapshots");
  EXPECT_CONTAINS(m, "keep one");
  // With dump_modify time yes each snapshot opens with ITEM: TIME.
  const std::string timed =
      "ITEM: TIME\n0.5\n" + one + "ITEM: TIME\n1.5\n" +
      lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.04 0.01"}, -1, "2000");
  const std::string t = read_error("dump_timed", timed);
  EXPECT_CONTAINS(t, "holds 2 snapshots");
}

// A general triclinic box (ITEM: BOX BOUNDS abc origin: a vector and an origin per row), and a
// file that starts with a UTF-8 byte-order mark: both read.
TEST(PackingDump, GeneralTriclinicBoxAndByteOrderMarkAreAccepted) {
  const std::string text =
      "\xEF\xBB\xBF" +
      lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.05 0.01"}, -1, "0",
                  "BOX BOUNDS abc origin pp pp pp\n1 0 0 -0.5\n0 1 0 -0.5\n0 0 0.2 0");
  EXPECT_EQ(read_packing_file(temp_file("dump_general", text)).centre[0], Vec3(0.1, 0.2, 0.05));
}

TEST(PackingDump, RowCountMustMatchNumberOfAtoms) {
  const std::vector<std::string> rows = {"1 1 0.1 0.2 0.05 0.01", "2 1 0.3 0.2 0.05 0.01"};
  const std::string fewer = lammps_dump("id type x y z radius", rows, 3);
  std::string m = read_error("dump_fewer", fewer);
  EXPECT_CONTAINS(m, line_of(fewer, "ITEM: ATOMS") +
                         "ITEM: ATOMS is followed by 2 rows; ITEM: "
                         "NUMBER OF ATOMS (line 3) says 3");
  m = read_error("dump_more", lammps_dump("id type x y z radius", rows, 1));
  EXPECT_CONTAINS(m, "followed by 2 rows; ITEM: NUMBER OF ATOMS (line 3) says 1");
  const std::string short_row = lammps_dump("id type x y z radius", {"1 1 0.1 0.2 0.05"});
  m = read_error("dump_short_row", short_row);
  EXPECT_CONTAINS(m, line_of(short_row, "1 1 0.1") +
                         "expected 6 columns (as ITEM: ATOMS on line 9 names), found 5");
  EXPECT_CONTAINS(read_error("dump_none", lammps_dump("id type x y z radius", {})),
                  "NUMBER OF ATOMS is 0: the dump holds no particle");
}

TEST(PackingDump, ScaledCoordinatesAreRefused) {
  for (const char* columns : {"id type xs ys zs radius", "id type xsu ysu zsu radius"}) {
    const std::string text = lammps_dump(columns, {"1 1 0.6 0.7 0.25 0.01"});
    const std::string m = read_error("dump_scaled", text);
    EXPECT_CONTAINS(
        m, line_of(text, "ITEM: ATOMS") + "ITEM: ATOMS names " + columns + ": scaled coordinates");
    EXPECT_CONTAINS(m, "dump x y z");
  }
  EXPECT_CONTAINS(read_error("dump_no_z", lammps_dump("id type x y radius", {"1 1 0.6 0.7 0.01"})),
                  "no centre columns; a dump needs x y z (or xu yu zu)");
}

TEST(PackingDump, MissingRadiusNeedsPackingRadius) {
  const std::string text = lammps_dump("id type x y z", {"1 1 0.1 0.2 0.05", "2 1 0.3 0.2 0.05"});
  const std::string m = read_error("dump_no_radius", text);
  EXPECT_CONTAINS(m, line_of(text, "ITEM: ATOMS") +
                         "ITEM: ATOMS names id type x y z: no radius or diameter column");
  EXPECT_CONTAINS(m, "packing.radius");
  const Particles p = read_packing_file(temp_file("dump_default_radius", text), 0.01);
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p.radius[0], 0.01);
  EXPECT_EQ(p.radius[1], 0.01);
  EXPECT_EQ(p.centre[1], Vec3(0.3, 0.2, 0.05));
  // A radius column and packing.radius: two radii for one sphere, refused as a plain x y z r
  // file with packing.radius is.
  for (const char* column : {"radius", "diameter"}) {
    const std::string both = lammps_dump(std::string("id x y z ") + column, {"1 0.1 0.2 0.3 0.02"});
    SCOPED_TRACE(column);
    beampack::testing::expect_error<InputError>(
        [&] { read_packing_file(temp_file("dump_both_radii", both), 0.01); },
        "packing.radius gives one too");
  }
}

TEST(PackingDump, EveryValueCheckOfPlainFilesApplies) {
  const std::string columns = "id type vx x radius y z";  // x is column 4, the radius column 5
  auto error = [&](const std::string& row) {
    const std::string text = lammps_dump(columns, {"1 1 0 0.1 0.01 0.2 0.3", row});
    return std::make_pair(read_error("dump_values", text), line_of(text, row));
  };
  auto [m, at] = error("2 1 0 0.1 -1 0.2 0.3");
  EXPECT_CONTAINS(m, at + "radius r = -1: must be > 0");
  std::tie(m, at) = error("2 1 0 nan 0.01 0.2 0.3");
  EXPECT_CONTAINS(m, at + "column 4 'nan' is not finite");
  std::tie(m, at) = error("2 1 0 0.1 0.01 abc 0.3");
  EXPECT_CONTAINS(m, at + "column 6 'abc' is not a number");
  std::tie(m, at) = error("2 1 0 0.1 1e-120 0.2 0.3");
  EXPECT_CONTAINS(m, at + "radius r = 1e-120: its volume");
  std::tie(m, at) = error("2 1 0 0.1 inf 0.2 0.3");
  EXPECT_CONTAINS(m, at + "column 5 'inf' is not finite");
  // An unused column is not read: a velocity that is not a number does not stop the dump.
  EXPECT_EQ(
      read_packing_file(temp_file("dump_unused", lammps_dump(columns, {"1 1 - 0.1 0.01 0.2 0.3"})))
          .size(),
      1u);
}

TEST(PackingDump, MalformedHeadersAreRefused) {
  EXPECT_CONTAINS(read_error("dump_unknown_item", "ITEM: TIMESTEP\n0\nITEM: ENTRIES c_1\n1\n"),
                  ":3: ITEM: ENTRIES c_1: not an item of a LAMMPS text dump");
  EXPECT_CONTAINS(
      read_error("dump_atoms_first", "ITEM: ATOMS id x y z radius\n1 0.1 0.2 0.3 0.01\n"),
      ":1: ITEM: ATOMS before ITEM: NUMBER OF ATOMS");
  EXPECT_CONTAINS(read_error("dump_bad_count", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2.5\n"),
                  ":4: ITEM: NUMBER OF ATOMS '2.5': must be one whole number >= 0");
  EXPECT_CONTAINS(read_error("dump_no_atoms", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\n"),
                  "a dump without ITEM: ATOMS holds no particle");
  // A plain file stays plain when only a comment mentions ITEM:.
  EXPECT_EQ(read_packing_file(temp_file("plain_item_comment", "# ITEM: ATOMS\nx y z r\n1 2 3 1\n"))
                .size(),
            1u);
}

TEST(PackingDump, DemBedRowsAsADumpGiveTheSameParticles) {
  const std::string path = std::string(BEAMPACK_DATA_DIR) + "/dem_bed_28367_r0.01.xyz";
  if (!fs::exists(path)) GTEST_SKIP() << "shared data not present at " << path;
  std::ifstream bed(path);
  std::string plain, line;
  std::vector<std::string> with_radius, without_radius;
  for (int id = 1; id <= 50 && std::getline(bed, line); ++id) {
    plain += line + "\n";
    std::istringstream xyz(line);
    std::string x, y, z;
    xyz >> x >> y >> z;  // the file's own text, so both readers parse the same digits
    with_radius.push_back(std::to_string(id) + " 1 " + z + " 0.01 " + x + " 0 " + y);
    without_radius.push_back(std::to_string(id) + " 1 " + x + " " + y + " " + z);
  }
  ASSERT_EQ(with_radius.size(), 50u);
  const Particles expected = read_packing_file(temp_file("dem_50.xyz", plain), 0.01);
  ASSERT_EQ(expected.size(), 50u);
  EXPECT_TRUE(
      same_packing(read_packing_file(temp_file(
                       "dem_50_radius.dump", lammps_dump("id type z radius x vx y", with_radius))),
                   expected));
  EXPECT_TRUE(same_packing(
      read_packing_file(temp_file("dem_50.dump", lammps_dump("id type x y z", without_radius)),
                        0.01),
      expected));
}
