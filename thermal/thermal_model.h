#pragma once
// The heat half of the staggered scheme (MODEL.md sections 4-5): conduction between touching
// particles and with walls, the generalised trapezoidal step (3.10)/(3.11), phase change by
// latent-heat bands (paper, section 4), vaporised particles removed, and an energy ledger.
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <vector>

#include "../geometry/contact.h"
#include "../geometry/particles.h"
#include "conduction.h"
#include "material.h"
#include "solvers.h"

namespace beampack {

// M multiplies every temperature rise (MODEL.md section 4): at M = 1e12 the quick preset's peak was
// 1.2e8 K, and it grows as M: 1.2e286 K at M = 1e290, without a word.
inline constexpr Cap kTimeScalingCap{
    1e12,
    "(1e6 times the paper's M = 1e6; M multiplies every temperature rise, and far "
    "beyond it they overflow)"};

struct ThermalSpec {
  double phi = 1;  // thermal.phi: 1 backward Euler, 1/2 Crank-Nicolson, 0 explicit
  // thermal.time_scaling: M of section 4.1, (4.5), divides m C: every temperature rise is M times
  // what the absorbed energy gives (one pulse heats as M would). 1e6 as in the paper; 1 for the
  // physical rise of the energy injected.
  double time_scaling = 1e6;
  std::string solver = "auto";  // thermal.solver: fixed-point | cg | direct | auto
  double tolerance = 1e-10;     // thermal.tolerance: relative, see solvers.h
  int max_iterations = 1000;    // thermal.max_iterations: fixed-point and cg
  // thermal.max_substeps: phi < 1 beyond its step limit (monotone_step_limit) is split into at
  // most this many sub-steps; more would be needed -> InputError.
  int max_substeps = 1000;
  // Predictor-corrector passes of the phase step: stop when no new band is crossed.
  int max_phase_corrections = 4;
  std::vector<Wall> walls;
  // Work only on the conducting components with something to do (a deposit, temperatures that
  // differ, a wall at another temperature; without conducting contacts each particle is its own
  // component) while they are under 3/4 of the live particles; the others are at rest,
  // theta^{n+1} = theta^n exactly. false: every step solves every particle.
  bool skip_resting = true;

  void validate() const;
};

// Every joule absorbed is stored as heat, carried off by vaporised particles or lost to walls:
// absorbed = stored + vaporized + walls, to the solver tolerance and the rounding of each rise
// into its temperature (a rise below ~1e-16 of the temperature is lost, and the ledger opens by
// it). Stored is the M-scaled sum of (m C_eff / M) (theta^{n+1} - theta^n), as the particles keep
// them, over steps and live particles.
struct ThermalLedger {
  double absorbed = 0;   // J, sum of the dH given to step()
  double stored = 0;     // J, in live particles, relative to their initial temperatures
  double vaporized = 0;  // J, stored in particles when they vaporised
  double walls = 0;      // J, net heat into the walls
  double imbalance() const { return absorbed - stored - vaporized - walls; }
};

struct StepReport {
  std::vector<std::uint32_t> vaporized;      // particles removed in this step
  std::vector<std::uint32_t> phase_changed;  // live particles now solid <-> liquid (optics change)
  std::string solver =
      "none";          // fixed-point | cg | direct | explicit | diagonal | none (or all at rest)
  int iterations = 0;  // summed over solves and sub-steps
  int solves = 0;      // linear solves (predictor + corrector passes, all sub-steps)
  int substeps = 1;
  double contraction_estimate = 0;  // dt phi max_i (2 sum_j G_ij + W_i) / c_i, see solvers.h
  bool conduction_ran = false;  // false: no contact conducts (K = 0) or every component was at rest
  // Particle rows solved, summed over sub-steps (with skip_resting, the busy ones), and the live
  // particles, summed the same way: their ratio is the share of the step's work that was done.
  std::size_t solved_rows = 0;
  std::size_t live_rows = 0;
  // false: no particle the step worked on (with skip_resting: the busy ones; one at rest cannot
  // cross a band) was at or above theta_m before or after it.
  bool phases_ran = false;
  double phases_seconds = 0;     // wall time of the latent-heat work (section 4), all sub-steps
  bool phase_corrected = false;  // a band was crossed and the step re-solved with C_eff
  // The corrector stopped at max_phase_corrections while its last solve still crossed a new band:
  // that band's latent heat is missing from the step.
  bool phase_passes_capped = false;
  // Particles charged a latent band (C + dP/dtheta) for a crossing that their corrected step then
  // fell short of (the band slowed them before theta_m or theta_v), and the latent heat so
  // charged, sum of m dP/dtheta |theta1 - theta0| / M (J): the paper's section 4 charges the band
  // on the predictor's crossing, so a stiff step can take it again and again without a phase
  // change.
  std::size_t bands_short = 0;
  double band_heat_short = 0;
  bool symbolic_reused = false;  // direct: analysis kept from an earlier step
  bool factors_reused = false;   // direct: numeric factors kept too
};

class ThermalModel {
 public:
  struct Snapshot {
    std::vector<double> temperature;
    std::vector<Phase> phase;
    std::vector<std::uint8_t> alive;
    std::vector<double> stored;
    ThermalLedger ledger;
    // The state's name (unique across models): restoring the state now or the one before the
    // model's last step keeps its record of the components that may not be at rest.
    std::uint64_t serial = 0;
    // The temperature the solve measures from (reference_): a model without walls takes it on
    // restore, so a model built on other starting temperatures goes on with the same digits.
    double reference = 0;
  };

  // Validates the spec and materials; sets each live particle's phase from its temperature
  // (InputError for one at or above theta_v or with an unknown material id).
  ThermalModel(Particles& particles, std::vector<Material> materials, ThermalSpec spec);

  // The contact graph to conduct over (find_contacts). Removed particles conduct nothing from
  // their removal on; drop_removed_contacts trims their entries, without a new search.
  void set_contacts(const std::vector<Contact>& contacts);
  // After vaporisations: drops the contacts of removed particles once they are more than
  // `min_fraction` of the list (until then the matrix holds them as zeros and keeps its pattern,
  // so it is updated in place and the direct solver keeps its analysis). The list stays what
  // find_contacts gives for the live particles (positions never change), without the search.
  void drop_removed_contacts(double min_fraction = 0.1);
  const std::vector<Contact>& contacts() const { return contacts_; }

  // One step of (3.10) over dt seconds with absorbed[i] joules deposited into particle i
  // (empty: none), phase change and vaporisation included.
  StepReport step(double dt, const std::vector<double>& absorbed);
  // The same, told which particles were heated: absorbed[i] is zero for every particle not in
  // `heated` (any order, repeats allowed). The step then reads only those deposits and, with
  // skip_resting after its first step, looks only at the components it solved last and the
  // heated ones (it still counts the live particles, and after a vaporisation compares the
  // live flags).
  StepReport step(double dt, const std::vector<double>& absorbed,
                  std::span<const std::uint32_t> heated);

  const ThermalLedger& ledger() const { return ledger_; }
  // Largest dt for which a step keeps the discrete maximum principle (no temperature leaves the
  // range of its neighbours', the walls' and its own plus the heat it absorbed):
  // min_i c_i / ((1 - phi) D_i), c_i = m_i min(C_S, C_L) / M (either phase the step may reach),
  // D_i the diagonal of L + W, where the explicit part's weight on
  // theta_i^n, c_i - (1 - phi) dt D_i, is still >= 0. For phi < 1/2 it is also the stability
  // limit; for 1/2 <= phi < 1 the step is stable beyond it but not monotone (Crank-Nicolson's
  // stiff modes flip sign every step: a 5-sphere chain cooled in one 1 us step went to -136 K).
  // Infinite for phi = 1 or without conduction.
  double monotone_step_limit() const;
  // The sub-steps a step of dt takes (dt / monotone_step_limit, rounded up); InputError beyond
  // thermal.max_substeps. The limit only grows as particles vaporise, so a caller may check a
  // step it will take before the run.
  int substep_count(double dt) const;
  // Thermal mass m_i C_i / M of particle i in its current phase (no bands).
  double thermal_mass(std::size_t i) const;

  // The conducting component of live particle i (contacts with G > 0 between live particles),
  // named by its lowest particle id, and whether it is an insulated cluster (>= 2 particles, no
  // wall touching it). For diagnostics and tests.
  std::uint32_t component_of(std::size_t i);
  bool in_insulated_cluster(std::size_t i);

  // Between steps the temperatures, phases and live flags of the particles belong to the model:
  // set them before constructing it, or through restore(); a change made behind its back can go
  // unseen by skip_resting.

  // Saves and restores temperatures, phases, live flags and the ledger (checkpoints; the stagger
  // uses undo_step). The contact list is not part of it: restore before calling set_contacts again.
  Snapshot save() const;
  void restore(const Snapshot& snapshot);
  // The stagger's redo of a step: back to the state before the last step() (temperatures,
  // phases, live flags, stored energy, ledger), from what that step changed (its rows) instead of
  // a copy of every particle. Once per step; RunError without a step to undo (also after a
  // step that failed: a step that throws leaves the model as it was before it).
  void undo_step();
  // Particle i's phase before the last step() (what the rays of that step saw).
  Phase phase_before_step(std::size_t i) const;
  // Calls f(i) for every particle the last step() changed (its rows): the others kept their
  // temperatures, phases and live flags.
  template <class F>
  void for_each_changed(F&& f) const {
    for (const Undo& u : undo_) f(u.particle);
  }

 private:
  // The linear system (L + W over a set of rows): every particle, row i being particle i, or the
  // live particles of the busy components, rows in ascending particle order. Components are
  // closed under conducting contacts, so the rows' system is the whole system restricted to them.
  struct System {
    std::vector<Eigen::Index> particle;  // of each row (empty for the whole system)
    SparseMatrix laplacian;              // L + W with the live mask applied
    std::vector<Eigen::Index> diag_pos;  // index of (k, k) in laplacian's values
    Eigen::VectorXd diagonal;            // D_k = sum_j G_kj + W_k (live)
    Eigen::VectorXd wall_source;         // sum_w g_w (theta_w - reference_) (live), W
    Eigen::VectorXd wall_conductance;    // sum_w g_w (live), W/K
    std::vector<std::uint8_t> live;
    // Clusters (>= 2 live particles joined by conducting contacts): cluster id per row (-1:
    // none) and the row grounded in each (solve_direct_grounded), marked by mark_clusters.
    std::vector<int> cluster;
    std::vector<Eigen::Index> ground;
    std::uint64_t pattern_version = 0;  // the direct solver keeps its analysis while unchanged
    bool has_conduction = false;        // some contact with G > 0
    std::size_t rows() const { return static_cast<std::size_t>(diagonal.size()); }
  };

  // A step's temperatures: absolute (the phase rules, the state and the ledger's stored heat) and
  // relative to reference_ (the solve and the walls' heat: a change below the last digit of a
  // temperature near 300 K keeps its digits there).
  struct StepTemperatures {
    Eigen::VectorXd theta0, theta1;  // K
    Eigen::VectorXd rel0, rel1;      // K - reference_
  };
  // A step's deposits: absorbed[i] / parts for i in particles (sorted), zero elsewhere.
  struct Heat {
    const std::vector<double>* absorbed;
    std::vector<std::uint32_t> particles;
    int parts = 1;
    double at(std::size_t i) const { return absorbed->empty() ? 0.0 : (*absorbed)[i] / parts; }
  };
  Heat checked_heat(const std::vector<double>& absorbed,
                    std::span<const std::uint32_t> given) const;
  void begin_undo();
  void put_back_changed();
  void clear_undo();
  static void add_substep(StepReport& report, const StepReport& sub);
  StepReport step_once(double dt, const Heat& heat);
  void book_heat_of_vaporised(const Heat& heat);
  Eigen::VectorXd heat_of_rows(const Heat& heat) const;
  void assemble_if_needed();
  bool live_contact_conducts() const;
  void set_wall_terms(Eigen::Index i);
  void assemble_anew(bool conducts);
  std::vector<Eigen::Index> live_flags_changed() const;
  void assemble_all();
  std::vector<Eigen::Index> update_live_set(const std::vector<Eigen::Index>& changed);
  void find_components();
  void collect_component(Eigen::Index from, std::uint32_t stamp, std::vector<Eigen::Index>& out);
  // The component of live particle i, named by its lowest particle id (i itself without a
  // conducting contact).
  Eigen::Index root_of(Eigen::Index i) const {
    return all_.has_conduction ? Eigen::Index{component_[static_cast<std::size_t>(i)]} : i;
  }
  void update_components(const std::vector<Eigen::Index>& touched);
  std::uint32_t next_stamp();
  void mark_clusters(System& s);
  void keep_energy_of_components(const System& s, const Eigen::VectorXd& weight,
                                 const Eigen::VectorXd& own, const Eigen::VectorXd& theta0,
                                 Eigen::VectorXd& theta1) const;
  bool insulated(std::uint32_t root) const;
  bool clustered(std::uint32_t root) const;
  bool select_busy(const Eigen::Ref<const Eigen::VectorXd>& theta0, const Heat& heat,
                   std::size_t live);
  std::vector<Eigen::Index> busy_rows_of_all(const Eigen::Ref<const Eigen::VectorXd>& theta0,
                                             const Heat& heat) const;
  std::vector<Eigen::Index> busy_rows_of_restless(const Eigen::Ref<const Eigen::VectorXd>& theta0,
                                                  const Heat& heat);
  std::vector<Eigen::Index> busy_rows_kept_and_new(const Eigen::Ref<const Eigen::VectorXd>& theta0,
                                                   const Heat& heat);
  void build_busy_system(std::vector<Eigen::Index> rows);
  Eigen::VectorXd thermal_masses() const;
  void count_bands_short(const Eigen::VectorXd& theta0, const Eigen::VectorXd& theta1,
                         const std::vector<std::uint8_t>& bands, StepReport& report) const;
  Eigen::VectorXd thermal_masses_with_bands(const Eigen::VectorXd& theta0,
                                            const std::vector<std::uint8_t>& bands) const;
  void solve(double dt, const Eigen::VectorXd& c, const Eigen::VectorXd& dh, StepTemperatures& t,
             StepReport& report);
  void solve_relative(const System& s, double dt, const Eigen::VectorXd& c,
                      const Eigen::VectorXd& theta0, const Eigen::VectorXd& dh,
                      Eigen::VectorXd& theta1, StepReport& report);
  SparseMatrix& step_matrix(const System& s, double implicit, const Eigen::VectorXd& c);
  bool solve_change(const SparseMatrix& a, const Eigen::VectorXd& c, const Eigen::VectorXd& drive,
                    double rho, const Eigen::VectorXd& theta0, Eigen::VectorXd& theta1,
                    StepReport& report) const;
  void solve_direct_grounded(const System& s, SparseMatrix& a, const Eigen::VectorXd& w,
                             const Eigen::VectorXd& rhs, Eigen::VectorXd& theta1,
                             StepReport& report);
  double contraction_estimate(const System& s, double dt, const Eigen::VectorXd& c) const;
  bool phase_work_needed(const Eigen::VectorXd& theta0, const Eigen::VectorXd& theta1) const;
  void correct_phases(double dt, const Eigen::VectorXd& dh, Eigen::VectorXd& c, StepTemperatures& t,
                      StepReport& report);
  void account(double dt, const Eigen::VectorXd& c, const StepTemperatures& t,
               const Eigen::VectorXd& dh);
  void update_phases(const Eigen::VectorXd& theta1, StepReport& report);
  void remember(std::size_t i);

  void check_particle_count(const char* when) const;

  Particles& p_;
  std::size_t particle_count_;  // p_.size() when the model took them: every array is of it
  std::vector<Material> materials_;
  ThermalSpec spec_;
  WallCoupling walls_;
  bool has_walls_ = false;
  std::vector<Contact> contacts_;
  // Each particle's contacts in contacts_, and a bound on the contacts with a removed end: the
  // exact count when the list was set, plus the contacts of each particle removed since (undone
  // removals leave it high). drop_removed_contacts looks at the list only once the bound reaches
  // its threshold (it copied the list at every vaporisation: 3.7% of a 10^6 run's profile).
  std::vector<std::uint32_t> contact_degree_;
  std::size_t removed_contacts_bound_ = 0;
  static constexpr std::size_t kBoundUnknown = std::numeric_limits<std::size_t>::max();
  std::vector<double> g_;    // G_ij per contact
  System all_;               // every particle
  System busy_;              // the busy components' particles (skip_resting)
  bool solve_busy_ = false;  // this step solves busy_ (the others are at rest)
  // The step's rows: every particle (row i is particle i) or busy_'s particles.
  Eigen::Index rows() const {
    return solve_busy_ ? static_cast<Eigen::Index>(busy_.particle.size())
                       : static_cast<Eigen::Index>(p_.size());
  }
  std::size_t particle_of(Eigen::Index row) const {
    return static_cast<std::size_t>(solve_busy_ ? busy_.particle[static_cast<std::size_t>(row)]
                                                : row);
  }
  std::uint64_t assembly_ = 0;       // counts assemblies of all_: busy_ is cut from one of them
  std::uint64_t busy_assembly_ = 0;  // the assembly busy_ was cut from
  std::uint64_t versions_ = 1;  // pattern versions handed out (all_ and busy_ share the solver)
  // Connected component of each live particle under conducting contacts: its lowest particle id
  // (kNoComponent for the others). By that id: the component's size and whether a wall touches it.
  static constexpr std::uint32_t kNoComponent = std::numeric_limits<std::uint32_t>::max();
  std::vector<std::uint32_t> component_;
  std::vector<std::uint32_t> component_size_;
  std::vector<std::uint8_t> component_walled_;
  std::vector<std::uint32_t> visited_;  // walks over the contacts (update_components): stamps
  std::uint32_t stamp_ = 0;
  std::vector<int> cluster_of_root_;  // mark_clusters' scratch, by component id
  std::vector<Eigen::Index> row_of_;  // build_busy_system's scratch: -1 between calls
  // The live flags the model flipped since all_ was assembled (flips_known_: no others changed).
  std::vector<Eigen::Index> flipped_;
  bool flips_known_ = false;
  std::size_t live_count_ = 0;  // live particles at the last assembly
  // skip_resting without a scan of every particle: every component not at rest (temperatures
  // that differ, a wall at another temperature) holds a particle in restless_, the rows solved
  // in the last step (with its sub-steps). False before the first step, after a new assembly,
  // a whole solve or a restore from elsewhere: the next step looks at every particle.
  std::vector<Eigen::Index> restless_;
  bool restless_known_ = false;
  std::uint64_t serial_ = 0;              // the state's name (new_serial), kept in snapshots
  std::uint64_t serial_before_step_ = 0;  // the name of the state the last step started from
  // What the last step() changed, for undo_step: each particle's state before its first change.
  struct Undo {
    std::size_t particle;
    double temperature, stored;
    Phase phase;
    std::uint8_t alive;
  };
  std::vector<Undo> undo_;
  std::vector<std::int32_t> undo_slot_;  // each particle's entry in undo_, -1: left alone
  ThermalLedger undo_ledger_;
  bool undo_ready_ = false;
  std::uint64_t clusters_assembly_ = 0;  // the assembly all_'s clusters were marked for
  mutable double limit_ = 0;             // monotone_step_limit of the assembly limit_assembly_
  mutable std::uint64_t limit_assembly_ = 0;
  // The temperature the solve measures from: the first wall's, or without walls the coolest live
  // particle's at the start. L 1 = 0, so the shift moves only the wall sources, to 0 at a wall of
  // that temperature; a particle held near it by a wall of 1e9 W/K then changes by digits a
  // temperature near 300 K cannot hold, and they still reach the solver (before: CG stopped at
  // once, heat imbalance 1); the ledger books what the particle keeps. Without walls, a bed warmed
  // by 1e-12 K a step: from 0 K the factorisation's round-off in theta (1e-16 of 300 K) opened
  // the ledger by 3.6e-5. Kept in snapshots and states (restore takes it without walls).
  double reference_ = 0;
  bool dirty_ = true;                   // all_'s values out of date (contacts or live set)
  bool pattern_dirty_ = true;           // the contacts changed: all_ is assembled anew
  std::vector<double> contact_values_;  // -G of each off-diagonal of all_.laplacian, as if live
  DirectSolver direct_;
  SparseMatrix step_matrix_;  // step_matrix's, of the system whose pattern_version it names
  std::uint64_t step_matrix_version_ = 0;
  std::vector<double> stored_;  // J per particle since the start
  ThermalLedger ledger_;
};

}  // namespace beampack
