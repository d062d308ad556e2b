#pragma once
// Rays through the packing: Fresnel bounces, absorbed energy per particle, an energy ledger
// (MODEL.md sections 3 and 5, paper (3.3)).
//
// Determinism: rays are processed in chunks of consecutive rays; each chunk records its events
// (energy into a particle, escaped, cut off) per ray in the ray's order, and the chunks are summed
// in chunk order, one at a time, as they finish: every sum runs in ray order. Every search finds
// the same nearest hit in double. Deposits and ledger are therefore bit-identical for any thread
// count, chunk size, packets or single rays, Embree or grid.
//
// Cost: a ray in free flight changes nothing (its state holds the path clock at its segment's
// origin), and an advance runs only the chunks with an event before its end.
//
// Particles in phase vapor must be removed (remove_particles); liquid ones use n_liquid.
#include <complex>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "../geometry/particles.h"
#include "beam.h"
#include "embree_scene.h"
#include "sphere_grid.h"
#include "state_io.h"

namespace beampack {

struct MaterialOptics {
  std::complex<double> n_solid{1.4, 0.0};   // optics.n_solid: n_hat of a solid particle
  std::complex<double> n_liquid{1.0, 0.0};  // optics.n_liquid: "approximately 1" in the paper
  double mu_hat = 1.0;
};

// The beam's polarisation: unpolarised (2.22), the default, or linear, its electric field at
// angle psi in the beam's disk from the axis u towards v of polarisation_axes (u is +z, or +x for a
// beam entering by a z face, projected onto the disk; for the +x beam u = +z, v = -y). Each ray
// then carries its field through its reflections (fresnel.h reflect_polarised), and gamma of (2.18)
// at a hit is the angle between that field and the plane of incidence.
struct Polarisation {
  bool linear = false;
  double psi = 0.0;  // rad, in [0, pi]; optics.polarisation in degrees
};

// How bounced rays find their next sphere (same answer bit for bit; docs/bench/optics.md):
// Embree single rays, waves of incoherent Embree packets, or waves of interleaved walks through a
// uniform grid (the default: measured fastest).
enum class BounceSearch { embree, packets, grid };

// One straight piece of a ray's path: from its segment origin to the hit or the box exit.
struct RaySegment {
  Vec3 from, to;
  double energy;  // J carried along it
};

inline constexpr std::size_t kMaxChunkRays = 256;
inline constexpr unsigned kMaxSpheresPerPrimitive = 64;

struct OpticsSpec {
  std::vector<MaterialOptics> materials = std::vector<MaterialOptics>(1);  // by Particles::material
  double cutoff = 1e-10;      // optics.cutoff: epsilon, relative to the ray's initial energy
  int max_bounces = 1000;     // optics.max_bounces
  Polarisation polarisation;  // optics.polarisation
  bool packets = true;        // primary rays in coherent 16-ray packets (false: single rays)
  BounceSearch bounce_search = BounceSearch::grid;
  double grid_cell_factor = 3.0;  // grid cell edge / largest radius (measured best of 1.5-4)
  // Background: every update under 4 ms at 1e6, the rebuild off the critical path (BENCHMARKS.md).
  SceneUpdate scene_update = SceneUpdate::background;
  unsigned spheres_per_primitive = 1;  // Embree primitive = cluster of this many spheres
  // Embree's device configuration (rtcNewDevice), e.g. "max_isa=sse4.2" to trace as on a machine
  // without AVX2 (the tests trace under each ISA: Embree splits packets wider than its own).
  std::string embree_config;
  // Rays per chunk (1-256): an advance runs only the chunks with an event before its end. Small
  // chunks leave more of them alone under short budgets (1e6 spheres, 10^5 rays, the paper's dt:
  // 15% of chunks run with 64, 44% with 256); whole pulses trace their bounces faster in large
  // ones (waves of more rays). A Simulation takes 64 for a fixed thermal.dt, 256 otherwise,
  // whatever its spec says (checked all the same). Results do not depend on it.
  std::size_t chunk_rays = 256;
  // A launch finds its rays' first hits at once (in coherent packets). A ray the beam launched
  // before too, from the same point on the same start plane in the same direction, meets the
  // sphere it met then, if that is still there: particles only disappear, so it stays the
  // nearest. Those hits are reused, not traced: a repeated beam's primaries cost a copy. Same
  // results either way; off for a beam that changes every pulse (beam.resample), where it would
  // only keep a copy of each pulse.
  bool reuse_primaries = true;
};

// InputError for a tuning value out of range (grid_cell_factor, chunk_rays, spheres_per_primitive):
// a Tracer checks its spec with it, a Simulation the caller's before it picks chunk_rays itself.
// embree_config goes to Embree as it is.
void check_optics_tuning(const OpticsSpec& spec);

// Every joule is in exactly one bin once no ray is live: injected = absorbed + escaped + cutoff.
struct OpticsLedger {
  double injected = 0.0;
  double absorbed = 0.0;
  double escaped = 0.0;
  double cutoff = 0.0;
  double in_flight() const { return injected - absorbed - escaped - cutoff; }
  // What the four sums above have rounded away (add_compensated): they take millions of ray
  // energies a pulse, and plain sums drifted (a flat beam's twenty pulses of 1e6 rays: the ledger
  // open by 1.5e-10 of the injected energy).
  double injected_low = 0.0, absorbed_low = 0.0, escaped_low = 0.0, cutoff_low = 0.0;
};

// A ray array: growing it leaves the new elements unwritten (a launch writes every field of every
// ray it adds), so a launch does not first zero its whole pulse of rays on one thread.
template <class T>
struct Unfilled : std::allocator<T> {
  template <class U>
  struct rebind {
    using other = Unfilled<U>;
  };
  Unfilled() = default;
  template <class U>
  Unfilled(const Unfilled<U>&) noexcept {}
  template <class U>
  void construct(U* p) noexcept(std::is_nothrow_default_constructible_v<U>) {
    ::new (static_cast<void*>(p)) U;
#if defined(BEAMPACK_POISON_GROWN_ARRAYS)  // sanitizer builds: a forgotten field reads as NaN / ~0
    std::memset(static_cast<void*>(p), 0xFF, sizeof(U));
#endif
  }
  // Copies and other constructions: std::allocator_traits' own (placement new).
};
template <class T>
using RayArray = std::vector<T, Unfilled<T>>;

// The state of every ray, copyable so a driver can redo a time step (MODEL.md section 5 step 4).
struct RayState {
  // Per ray (structure of arrays). A ray's current segment starts at origin, which it passed
  // when the path clock read start_clock; its next event is t_next along the segment: a hit on
  // `next_particle`, or leaving the box (kNoParticle). t_next < 0: to be traced (after a hit, or
  // when the particle ahead was removed; a launch traces the first segment). So a ray in free
  // flight changes nothing in its state: the clock alone moves on.
  RayArray<Vec3> origin, direction, normal;  // normal: at the next hit
  RayArray<double> energy, initial_energy, start_clock, t_next;
  RayArray<std::uint32_t> last_particle, next_particle;
  RayArray<std::int32_t> bounces;
  RayArray<std::uint8_t> live;
  // A linearly polarised beam's rays carry their unit electric field; unpolarised ones have none
  // (the array is neither allocated nor copied).
  bool polarised = false;
  RayArray<Vec3> field;
  OpticsLedger ledger;
  // The path clock: c times the time the rays have flown, summed over advances (each adds its
  // budget, or the pulse's flight). Back to 0 at every launch; live rays' start_clock move with it.
  double clock = 0.0;
  std::uint64_t primary_segments = 0;  // Embree queries from the entry plane
  std::uint64_t bounced_segments = 0;  // queries after a bounce (or a retrace after a removal)
  std::uint64_t hits = 0;
  std::uint64_t reused_primaries = 0;  // first hits taken from an earlier launch (not traced)
  std::size_t live_count = 0;

  // Calls f on a pointer to every per-ray array member: compaction, checkpoints and the undo
  // record go through this one list, so a field added above is added here and nowhere else.
  template <class F>
  static void for_each_member(bool polarised, F&& f) {
    f(&RayState::origin), f(&RayState::direction), f(&RayState::normal), f(&RayState::energy);
    f(&RayState::initial_energy), f(&RayState::start_clock), f(&RayState::t_next);
    f(&RayState::last_particle), f(&RayState::next_particle), f(&RayState::bounces),
        f(&RayState::live);
    if (polarised) f(&RayState::field);
  }
  template <class F>
  void for_each_array(F&& f) {
    for_each_member(polarised, [&](auto member) { f(this->*member); });
  }
  template <class F>
  void for_each_array(F&& f) const {
    for_each_member(polarised, [&](auto member) { f(this->*member); });
  }

  // Checkpoints.
  void write(StateWriter& out) const;
  void read(StateReader& in);
  // InputError naming `source` when live_count is not the number of live flags.
  void check_live_count(const std::string& source) const;
  void check_lengths(const std::string& source) const;  // every per-ray array one entry per ray
  // InputError when a value is beyond what a trace can hold: a particle index past `particles`,
  // an energy or clock that is negative or not finite, a flag other than 0 or 1.
  void check_values(std::size_t particles, const std::string& source) const;
};

class Tracer {
 public:
  // Checks the particles and the spec's values. The ray scene and the bounce grid are built on
  // first need (a launch, or an advance with live rays), so Embree's own errors (a device
  // configuration it refuses) come from build_scene: a tracer that never traces builds neither.
  // The tracer keeps a reference to `particles`: they must outlive it, keep their count, and
  // change only through it (remove_particles) or in their temperatures and phases.
  Tracer(const Particles& particles, OpticsSpec spec);
  Tracer(const Particles&& particles, OpticsSpec spec) = delete;  // a temporary would dangle
  ~Tracer();

  // Builds the ray scene (and the bounce grid) now, if not yet built: for a caller that wants its
  // time and its errors at set-up rather than at the first launch.
  void build_scene();
  bool has_scene() const { return scene_ != nullptr; }
  // Updates of the ray scene's structure since its build (EmbreeScene::rebuilds).
  std::size_t scene_rebuilds() const;
  // Background rebuilds of the ray scene that failed (the traces went on with the structure
  // before, correct and slower), and the last one's message (EmbreeScene::poll_rebuild).
  std::size_t failed_scene_rebuilds() const;
  std::string last_failed_scene_rebuild() const;
  // Finishes a background rebuild of the ray scene in flight or due, and takes it (benchmarks,
  // and a caller about to time something).
  void finish_scene_rebuild();

  // Adds the beam's rays (energy E_k = I_k A_r tau each) to the live rays, starting on a plane
  // upstream of every particle, in the beam's (tiled) order: 16 consecutive rays are a packet.
  // Finds their first hits (OpticsSpec::reuse_primaries), so their chunks' next events are known.
  void launch(const Beam& beam, double pulse_duration);
  void launch(const Beam& beam, std::span<const double> energies);

  // Advances every live ray by at most path_budget of path (c * dt; infinity: to the end),
  // adding absorbed energy to deposits[particle] (resized to the particle count if smaller).
  // With `deposited`, each particle whose deposit this call turns from zero to non-zero is
  // appended to it. Returns the number of rays still live.
  std::size_t advance(double path_budget, std::vector<double>& deposits,
                      std::vector<std::uint32_t>* deposited = nullptr);

  // Ray paths for output (rays_NNNN.vtp): while on, every completed segment is kept, in chunk
  // and ray order; take_segments() hands them over and clears the store.
  void record_segments(bool on) { record_segments_ = on; }
  std::vector<RaySegment> take_segments() { return std::exchange(segments_, {}); }

  // The most path any ray travelled in the last advance(): with an infinite budget, the flight
  // of the pulse (the step length of thermal.dt = "pulse" is this over c).
  double last_advance_path() const { return last_advance_path_; }
  // Chunks of rays in the last advance: those with a live ray, and those it ran (the others were
  // in free flight throughout and cost nothing).
  std::size_t last_chunks_live() const { return last_chunks_live_; }
  std::size_t last_chunks_run() const { return last_chunks_run_; }
  bool has_live_rays() const { return state_.live_count > 0; }
  // Energy the live rays carry, summed in ray order: between advances, ledger().in_flight().
  double energy_in_flight() const;
  const OpticsLedger& ledger() const { return state_.ledger; }
  std::uint64_t primary_segments() const { return state_.primary_segments; }
  std::uint64_t bounced_segments() const { return state_.bounced_segments; }
  std::uint64_t hits() const { return state_.hits; }
  std::uint64_t reused_primaries() const { return state_.reused_primaries; }

  // Removed particles are never hit again; a ray heading for one is traced again when it gets
  // there (the removal costs what Embree and the grid pay, not a look at every ray).
  void remove_particles(std::span<const std::uint32_t> ids);
  // Drops the ended rays from the state (keeps the ledger and counters).
  void compact();
  // The same once more than half the rays have ended (the live ones keep their order, so
  // deposits and ledger do not change): bounds the ended rays a running chunk steps over.
  void compact_if_sparse();

  RayState save() const { return state_; }
  void restore(const RayState& state);
  // restore()'s checks alone (InputError naming `when`), for a caller that must check every part
  // of a state before it changes any.
  void check_restorable(const RayState& state, const char* when) const;
  // The first hit of every ray of the last beam launched, by the ray's place k in the beam
  // (OpticsSpec::reuse_primaries): the beam's direction and start plane, ray k's point on the
  // beam's disk, and what its query found.
  struct FirstHits {
    Vec3 direction = Vec3::Zero();
    double upstream = 0.0;
    std::vector<Vec3> origin, normal;
    std::vector<double> t;
    std::vector<std::uint32_t> particle;
  };
  // Checkpoints: the first hits kept for reuse, so a resumed run traces (and counts) what the
  // uninterrupted one would. restore() leaves them alone: they stay true whatever the rays.
  // Reading checks their lengths, particle indices and distances and changes nothing.
  void write_first_hits(StateWriter& out) const;
  FirstHits read_first_hits(StateReader& in) const;
  void restore_first_hits(FirstHits hits) { first_hits_ = std::move(hits); }

  // While on, every advance keeps what it changes (the rays of the chunks it ran, the ledger,
  // counters, clock and recorded segments), and undo_advance() puts them back: the stagger's
  // redo of a step costs what the step touched, not a copy of every ray. Anything else that
  // changes the rays (launch, compaction, removal, restore) drops the record.
  void keep_undo(bool on);
  // Back to before the last advance (last_advance_path and the chunk counts are the advance's
  // before it again). RunError unless that advance was kept and nothing else changed the rays
  // since; once per advance.
  void undo_advance();

  // Built with the scene (so not before it), and only when bounced rays can exist.
  bool has_grid() const { return grid_ != nullptr; }
  const Box& box() const { return box_; }

 private:
  struct Chunk;
  // A launch under way: its beam and energies, start plane, the beam's field and the first new ray.
  struct Launch {
    const Beam& beam;
    std::span<const double> energies;
    double upstream;
    Vec3 field;
    std::size_t first;
  };
  void check_launch(const Beam& beam, std::span<const double> energies) const;
  void check_beam_points(const Beam& beam) const;
  // build_scene, then the scene takes a finished background rebuild or starts a due one
  // (SceneUpdate::background).
  void prepare_scene();
  void check_particle_count(const char* when) const;
  double start_plane(const Beam& beam) const;
  Vec3 beam_field(const Vec3& direction) const;
  void reset_first_hits_for(const Vec3& direction, double upstream, std::size_t count);
  std::size_t start_rays(const Launch& launch, std::size_t begin, std::size_t end);
  void start_ray(std::size_t r, const Vec3& origin, const Vec3& direction, double energy);
  bool rebase_clock();
  std::size_t find_first_hits(const Beam& beam, std::size_t first, std::size_t begin,
                              std::size_t end);
  bool reuse_first_hit(const Beam& beam, std::size_t k, std::uint32_t ray);
  void keep_first_hit(const Beam& beam, std::size_t k, std::uint32_t ray);
  double reflect_field(std::uint32_t r, const Vec3& normal, const MaterialOptics& m, Phase phase);
  void open_query(std::uint32_t ray);
  bool close_query(std::uint32_t ray);
  void trace_ids(const std::uint32_t* ids, std::size_t count, bool coherent);
  void trace_wave(const std::vector<std::uint32_t>& rays, Chunk& chunk);
  void trace_segment(std::uint32_t ray);
  bool step_ray(std::uint32_t ray, double end_clock, Chunk& chunk);
  void end_ray(std::uint32_t ray, double at, Chunk& chunk);
  void count_segment(std::uint32_t ray, Chunk& chunk) const;
  void run_chunk(Chunk& chunk, std::size_t begin, std::size_t end, double end_clock);
  void refresh_next_events(std::size_t first_chunk, std::size_t end_chunk = SIZE_MAX);
  void update_next_event(std::size_t chunk);
  double next_event_of_chunk(std::size_t begin, std::size_t end) const;
  void add_chunk(Chunk& chunk, std::vector<double>& deposits,
                 std::vector<std::uint32_t>* deposited);
  void trace_chunk(Chunk& chunk, std::size_t begin, std::size_t end, double end_clock);
  void trace_in_waves(Chunk& chunk, std::size_t begin, std::size_t end, double end_clock);
  static void sort_events_by_ray(Chunk& chunk, std::size_t begin, std::size_t end);

  const Particles& particles_;
  OpticsSpec spec_;
  std::unique_ptr<EmbreeScene> scene_;
  std::unique_ptr<SphereGrid> grid_;  // bounced rays (BounceSearch::grid, max_bounces > 1)
  std::size_t particle_count_ = 0;    // at construction: the count must stay
  std::vector<std::uint32_t> removed_unbuilt_;  // removed before the scene was built, in order
  Box box_;  // all particles grown by their radii: leaving it means escaped
  RayState state_;
  bool record_segments_ = false;
  std::vector<RaySegment> segments_;
  std::vector<Chunk> chunks_;  // per advance; kept so their event storage is reused
  // Per chunk of rays: the path clock of the earliest event among its live rays (-infinity: a
  // ray to trace; +infinity: none live). An advance runs only the chunks with an event before
  // its end; the others are in free flight, which changes nothing but the clock.
  std::vector<double> next_event_;
  std::vector<std::uint32_t> due_chunks_;  // per advance: the chunks it runs
  FirstHits first_hits_;
  // The undo record of the last advance: its totals as they were (each chunk it ran keeps the
  // rays it changed, chunks_[j] for due_chunks_[j]).
  struct Undo {
    bool on = false, held = false;
    OpticsLedger ledger;
    std::uint64_t primary = 0, bounced = 0, hits = 0;
    std::size_t live_count = 0;
    double clock = 0.0;
    double last_advance_path = 0.0;  // of the advance before
    std::size_t last_chunks_live = 0, last_chunks_run = 0;
    std::size_t segments = 0;  // recorded segments before it
  };
  Undo undo_;
  std::size_t select_due_chunks(double end_clock);
  void open_undo_record();
  std::size_t chunks_per_batch() const;
  void run_due_chunks(double end_clock, std::vector<double>& deposits,
                      std::vector<std::uint32_t>* deposited);
  // Keeps ray's state for undo_advance (when on) before an advance first changes it: the check
  // inline, since every step makes it; the copy out of line.
  void remember(std::uint32_t ray, Chunk& chunk) const {
    if (undo_.on) keep_before(ray, chunk);
  }
  void keep_before(std::uint32_t ray, Chunk& chunk) const;
  // What add_chunk sums during an advance, folded into state_ at its end: on cache lines of its
  // own, so the serial reduction never invalidates the lines the tracing threads keep reading
  // (RayState's array headers). Measured: sharing them made 2 threads ~40% slower in some runs.
  struct alignas(64) Totals {
    OpticsLedger ledger;
    std::uint64_t primary = 0, bounced = 0, hits = 0;
    std::size_t ended = 0;
    double flight = 0.0;
  };
  Totals totals_;
  double last_advance_path_ = 0.0;
  std::size_t last_chunks_live_ = 0, last_chunks_run_ = 0;
};

// Distance from o along unit d to the first far face the ray crosses: where it leaves the box
// when it passes through it. A ray beside the box gets the distance to the nearest far face's
// plane instead (an escaping ray's last flight); 0 when that plane is behind o.
double box_exit_distance(const Box& box, const Vec3& o, const Vec3& d);

}  // namespace beampack
