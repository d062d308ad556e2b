#include "thermal/solvers.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "geometry/error.h"

namespace beampack {

namespace {

// Below this many stored entries a product stays on one thread (a task costs more than it saves).
constexpr Eigen::Index kParallelEntries = 1 << 15;

// f(i, (a x)_i) for every row i of a symmetric a stored whole (compressed or not). Row i's sum runs
// over column i's entries in ascending row order, a_ji x_j = a_ij x_j added for j ascending from 0:
// the order of Eigen's column-major a * x, which adds a_ij x_j into y_i column after column. Rows
// are independent, so any split over threads gives the same bits.
template <class F>
void for_each_row_of_product(const SparseMatrix& a, const Eigen::VectorXd& x, const F& f) {
  auto rows = [&](Eigen::Index begin, Eigen::Index end) {
    for (Eigen::Index i = begin; i < end; ++i) {
      double sum = 0;
      for (SparseMatrix::InnerIterator it(a, i); it; ++it) sum += it.value() * x[it.index()];
      f(i, sum);
    }
  };
  if (a.nonZeros() < kParallelEntries) return rows(0, a.outerSize());
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, a.outerSize(), 2048),
                    [&](const tbb::blocked_range<Eigen::Index>& r) { rows(r.begin(), r.end()); });
}

[[noreturn]] void fixed_point_failure(const char* what, int k, double update, double ratio,
                                      double contraction_estimate) {
  std::ostringstream msg;
  msg << "thermal fixed-point iteration (3.11) " << what << " at iteration " << k
      << " (relative update " << update << ", update ratio " << ratio
      << ", contraction bound dt phi max_i(2 sum_j G_ij + W_i)/c_i = " << contraction_estimate
      << "; it bounds the iteration's spectral radius, which must be below 1): use "
         "thermal.solver = \"cg\", \"direct\" or \"auto\", or a smaller thermal.dt";
  throw SolverRefusal(msg.str());
}

// Whether a system's matrix and right-hand side are finite: a non-finite result from finite
// inputs is the solver's breakdown (a refusal), from non-finite ones a defect upstream (never a
// case for a fallback). Looked at only once a result is not finite.
bool finite_system(const SparseMatrix& a, const Eigen::VectorXd& rhs) {
  bool finite = rhs.allFinite();
  for (int k = 0; k < a.outerSize(); ++k)
    for (SparseMatrix::InnerIterator it(a, k); it; ++it) finite &= std::isfinite(it.value());
  return finite;
}

}  // namespace

Eigen::VectorXd symmetric_product(const SparseMatrix& a, const Eigen::VectorXd& x) {
  Eigen::VectorXd y(a.rows());
  for_each_row_of_product(a, x, [&](Eigen::Index i, double sum) { y[i] = sum; });
  return y;
}

SolveStats fixed_point_solve(const SparseMatrix& a, const Eigen::VectorXd& c,
                             const Eigen::VectorXd& rhs, Eigen::VectorXd& theta, double tolerance,
                             int max_iterations, double contraction_estimate) {
  // Divergence: the update grew this many times in a row. Stagnation: over a window the update
  // shrank so little that the cap would be reached long before the tolerance. Both are judged on
  // the update's capacity-weighted size |c^{1/2} u|: the iteration matrix I - c^{-1} A is
  // self-adjoint under it (c - A is symmetric), so a convergent iteration shrinks it by at least
  // its spectral radius every time. Its largest component can grow for a few iterations even
  // so (spheres of unequal size), which made convergent iterations "diverge" or "stagnate".
  constexpr int kGrowthLimit = 3;
  constexpr int kWindow = 20;
  const Eigen::VectorXd root_c = c.cwiseSqrt();
  double previous = 0, previous_size = 0;
  int growing = 0;
  std::vector<double> history;
  const bool finite_guess = theta.allFinite();  // before theta moves on
  Eigen::VectorXd update(theta.size());
  for (int k = 1; k <= max_iterations; ++k) {
    for_each_row_of_product(
        a, theta, [&](Eigen::Index i, double a_theta) { update[i] = (rhs[i] - a_theta) / c[i]; });
    theta += update;
    const double abs_u = update.cwiseAbs().maxCoeff();
    const double u = abs_u == 0 ? 0.0
                                : abs_u / std::max(theta.cwiseAbs().maxCoeff(),
                                                   std::numeric_limits<double>::min());
    const double size = update.cwiseProduct(root_c).stableNorm();  // no overflow at extreme c
    const double ratio = k > 1 && previous_size > 0 ? size / previous_size : 0.0;
    if (!std::isfinite(u) && !(finite_guess && c.allFinite() && finite_system(a, rhs)))
      throw RunError("thermal fixed-point iteration (3.11) met non-finite inputs at iteration " +
                     std::to_string(k));
    if (!std::isfinite(u))
      fixed_point_failure("diverged to a non-finite field", k, u, ratio, contraction_estimate);
    if (u <= tolerance) return {k, u};
    growing = ratio > 1.0 ? growing + 1 : 0;
    if (growing >= kGrowthLimit) fixed_point_failure("diverges", k, u, ratio, contraction_estimate);
    history.push_back(size);
    if (k > kWindow) {
      const double rate = std::pow(size / history[k - 1 - kWindow], 1.0 / kWindow);
      const double needed = std::log(tolerance / u) / std::log(std::min(rate, 1.0 - 1e-16));
      if (rate >= 1.0 || needed > 10.0 * (max_iterations - k))
        fixed_point_failure("stagnates", k, u, rate, contraction_estimate);
    }
    previous = u;
    previous_size = size;
  }
  fixed_point_failure("did not converge within thermal.max_iterations", max_iterations, previous,
                      0.0, contraction_estimate);
}

namespace {

// 1 / a_ii, or 1 where the diagonal is missing or zero: Eigen's DiagonalPreconditioner.
Eigen::VectorXd inverse_diagonal(const SparseMatrix& a) {
  Eigen::VectorXd inverse = Eigen::VectorXd::Ones(a.cols());
  for (Eigen::Index j = 0; j < a.outerSize(); ++j)
    for (SparseMatrix::InnerIterator it(a, j); it; ++it)
      if (it.index() == j && it.value() != 0) inverse[j] = 1.0 / it.value();
  return inverse;
}

}  // namespace

// Eigen's ConjugateGradient<Lower | Upper, DiagonalPreconditioner> step for step (its
// conjugate_gradient), with the products and the vector updates over threads: the products are
// Eigen's to the bit (for_each_row_of_product), the updates elementwise, and the dot products
// Eigen's own, in one thread. So the result is Eigen's, bit for bit, on any thread count.
SolveStats cg_solve(const SparseMatrix& a, const Eigen::VectorXd& rhs, Eigen::VectorXd& theta,
                    double tolerance, int max_iterations) {
  const Eigen::Index n = a.cols();
  const Eigen::VectorXd guess = theta, inverse = inverse_diagonal(a);
  Eigen::VectorXd residual(n), p(n), z(n), a_p(n);
  for_each_row_of_product(a, theta,
                          [&](Eigen::Index i, double a_theta) { residual[i] = rhs[i] - a_theta; });
  const double rhs_norm2 = rhs.squaredNorm();
  if (rhs_norm2 == 0) {
    theta.setZero();
    return {0, 0.0};
  }
  const double threshold =
      std::max(tolerance * tolerance * rhs_norm2, std::numeric_limits<double>::min());
  double residual_norm2 = residual.squaredNorm();
  int iterations = 0;
  if (!(residual_norm2 < threshold)) {  // as Eigen: a NaN residual iterates (and is caught below)
    for_each_row(n, [&](Eigen::Index i) { p[i] = inverse[i] * residual[i]; });
    double abs_new = residual.dot(p);
    while (iterations < max_iterations) {
      for_each_row_of_product(a, p, [&](Eigen::Index i, double a_pi) { a_p[i] = a_pi; });
      const double alpha = abs_new / p.dot(a_p);
      for_each_row(n, [&](Eigen::Index i) {
        theta[i] += alpha * p[i];
        residual[i] -= alpha * a_p[i];
      });
      residual_norm2 = residual.squaredNorm();
      if (residual_norm2 < threshold) break;
      for_each_row(n, [&](Eigen::Index i) { z[i] = inverse[i] * residual[i]; });
      const double abs_old = abs_new;
      abs_new = residual.dot(z);
      const double beta = abs_new / abs_old;
      for_each_row(n, [&](Eigen::Index i) { p[i] = z[i] + beta * p[i]; });
      ++iterations;
    }
  }
  const double error = std::sqrt(residual_norm2 / rhs_norm2);
  if (!theta.allFinite()) {
    // From finite inputs: CG broke down (a search direction of zero energy p^T A p), as it does
    // on a step matrix singular to doubles (two spheres at K = 1e20, dt G / c ~ 1e25), which the
    // factorisation grounds. From non-finite ones: a defect upstream.
    if (!(guess.allFinite() && finite_system(a, rhs)))
      throw RunError("thermal conjugate gradients returned a non-finite temperature change after " +
                     std::to_string(iterations) + " iterations");
    throw SolverRefusal(
        "thermal conjugate gradients broke down after " + std::to_string(iterations) +
        " iterations (a non-finite change from finite inputs): the step's matrix is too stiff "
        "for them (conductances beyond ~1e15 times the capacities per step); use "
        "thermal.solver = \"direct\" (or \"auto\"), or a shorter thermal.dt");
  }
  if (!(error <= tolerance)) {
    std::ostringstream msg;
    msg << "thermal conjugate gradients did not reach thermal.tolerance = " << tolerance
        << " within thermal.max_iterations = " << max_iterations << " (relative residual " << error
        << "): raise thermal.max_iterations or use thermal.solver = \"direct\"";
    throw SolverRefusal(msg.str());
  }
  return {iterations, error};
}

void DirectSolver::solve(const SparseMatrix& a, std::uint64_t pattern_version,
                         const Eigen::VectorXd& rhs, Eigen::VectorXd& theta) {
  symbolic_reused_ = analysed_ && pattern_version == pattern_version_;
  if (!symbolic_reused_) {
    ldlt_.analyzePattern(a);
    analysed_ = true;
    pattern_version_ = pattern_version;
    factored_values_.clear();
  }
  const double* v = a.valuePtr();
  const auto nnz = static_cast<std::size_t>(a.nonZeros());
  factors_reused_ = symbolic_reused_ && factored_values_.size() == nnz &&
                    std::equal(v, v + nnz, factored_values_.begin());
  if (!factors_reused_) {
    ldlt_.factorize(a);
    factored_values_.assign(v, v + nnz);
  }
  if (ldlt_.info() != Eigen::Success) {
    factored_values_.clear();
    throw RunError(
        "thermal direct solver: LDL^T factorisation failed (matrix not positive "
        "definite; non-positive heat capacity or time step?)");
  }
  theta = ldlt_.solve(rhs);
  if (!theta.allFinite()) throw RunError("thermal direct solver: non-finite temperature");
}

const char* auto_solver(double contraction, Eigen::Index rows, int max_iterations) {
  if (contraction <= 0.1) return "fixed-point";
  double cg_bound = kAutoCgBound;
  if (static_cast<double>(rows) > kAutoSmallRows) {
    const double size = static_cast<double>(rows) / kAutoSmallRows;
    const double within_iterations = (max_iterations / 8.0) * (max_iterations / 8.0);
    cg_bound = std::max(kAutoCgBound, std::min(kAutoCgBound * size * size, within_iterations));
  }
  return contraction <= cg_bound ? "cg" : "direct";
}

}  // namespace beampack
