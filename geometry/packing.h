#pragma once
// Packings: where the spheres are. Every generator is sequential and seeded with beampack::Rng,
// so the same seed gives the same packing on every machine and thread count.
#include <array>
#include <cstdint>
#include <string>

#include "particles.h"

namespace beampack {

struct PackingSpec {
  std::string source = "random-overlap";  // random-overlap | rsa | lattice | file
  std::size_t count = 1000;               // N_p
  double sample_size = 1e-3;              // D, edge of the cube [0, D]^3
  double radius_ratio = 0.325;  // L of the paper: R = L (D^3 / N_p)^(1/3) = L D / N_p^(1/3)
  double solid_fraction = 0.3;  // rsa target: N (4/3) pi R^3 / D^3
  std::uint64_t seed = 1;
  std::string file;          // x y z r columns or a LAMMPS dump (source = file)
  double file_radius = 0.0;  // radius for x y z files; 0: the file must give r
  double initial_temperature = 300.0;
};

Particles make_packing(const PackingSpec& spec);

// The radius R of a packing's spheres: R = L D / N^(1/3) for random-overlap and lattice (the
// paper's L, written so that D^3 never over- or underflows), D (3 phi / (4 pi N))^(1/3) for rsa;
// for a file, the median of its radii (the paper's R when sizes differ, remark after (3.11)),
// read from the file, 0 for an empty one.
double packing_radius(const PackingSpec& spec);
// The key that sets every sphere's radius, with its value (`packing.radius_ratio` = 0.325), or ""
// when the radii are a file's own: for messages about a radius the user did not write.
std::string radius_setting(const PackingSpec& spec);
// The largest radius a particle may have, m, and why, as error messages give it after
// "must be <= 1e+06" (a file's radius and packing.radius alike): at 1e20 m no ray met one.
constexpr double kMaxParticleRadius = 1e6;
constexpr const char* kMaxParticleRadiusWhy =
    "m (the largest sample.size; far larger spheres are lost to the ray scene's float bounds)";
// The checks every sphere of a packing file passes (a checkpoint's too): a radius in
// (0, kMaxParticleRadius], and centre +- radius finite. InputError prefixed by
// `where`, naming the file's column of x, y or z (centre_columns) that overflows.
void check_sphere(const Vec3& centre, double r, const std::array<std::size_t, 3>& centre_columns,
                  const std::string& where);
// What a library caller's particles must hold before a tracer or a simulation takes them: arrays
// of one length, every sphere as check_sphere asks (column k + 1 is coordinate k), temperatures
// finite and > 0 K, live flags 0 or 1. InputError naming the first particle that fails.
void check_particles(const Particles& particles);

// The middle radius (the mean of the middle two for an even count); 0 for no particles.
double median_radius(const Particles& particles);

// Generated packings are numbered along a Morton curve (neighbours in space are neighbours in
// memory); files keep their order.
// Paper, section 5: centres uniform in [0, D]^3, equal radii R = L (D^3 / N)^(1/3), overlaps
// allowed.
Particles random_overlap_packing(std::size_t count, double size, double radius_ratio,
                                 std::uint64_t seed);
// Random sequential addition of non-overlapping equal spheres inside [0, D]^3 to the target solid
// fraction; InputError when the fraction is not reached in bounded work (RSA jams near 0.38).
Particles rsa_packing(std::size_t count, double size, double solid_fraction, std::uint64_t seed);
// Simple cubic lattice of count = n^3 spheres, spacing a = D / n, centres at (k + 1/2) a,
// radius L a (with the paper's R / V^(1/3) = L, V = a^3).
Particles lattice_packing(std::size_t count, double size, double radius_ratio);
// Why a lattice cannot have `count` spheres ("": it can), for the run file's check.
std::string lattice_count_problem(std::size_t count);

// Columns x y z r (or x y z with default_radius > 0); '#' comments, blank lines and one header
// line (no column a number) before the data allowed; lines end at LF, CR LF or a CR alone.
// InputError with "path:line:" for missing columns, non-numbers (a typo in the first data line
// too), a second header, NaN/inf, r <= 0, a volume that is not a positive finite double, or a
// centre +- r that overflows; and, once read, two rows with one centre, naming both lines.
// A file whose first line starts with "ITEM:" is read as one snapshot of a LAMMPS / LIGGGHTS text
// dump (`dump ... custom ... x y z radius`): centre from x y z (else xu yu zu), radius from
// radius (else diameter / 2, else default_radius); scaled coordinates, several snapshots or a
// row count other than NUMBER OF ATOMS are refused, and each row passes the checks above.
Particles read_packing_file(const std::string& path, double default_radius = 0.0);
void write_packing_file(const std::string& path, const Particles& particles);

}  // namespace beampack
