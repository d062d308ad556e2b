#pragma once
// Solvers for the implicit step (3.10): A theta = rhs with A = diag(c) + dt phi (L + W),
// symmetric positive definite for phi > 0 (c > 0, L + W a weighted graph Laplacian plus a
// non-negative diagonal).
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <cstdint>
#include <vector>

namespace beampack {

using SparseMatrix = Eigen::SparseMatrix<double>;

// f(i) for every row i in [0, n), over threads when there are many (8192 or more); f writes row
// i alone, so the same bits on any thread count.
template <class F>
void for_each_row(Eigen::Index n, const F& f) {
  constexpr Eigen::Index kParallelRows = 8192;  // fewer: a task costs more than it saves
  if (n < kParallelRows) {
    for (Eigen::Index i = 0; i < n; ++i) f(i);
    return;
  }
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, n, 4096),
                    [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index i = r.begin(); i < r.end(); ++i) f(i);
  });
}

struct SolveStats {
  int iterations = 0;
  double error = 0;  // last relative update (fixed-point) or relative residual (cg)
};

// a x for a symmetric a stored whole (both triangles), rows over threads above a few thousand:
// the same bits as Eigen's a * x on any thread count (see solvers.cpp). It sums column i for row
// i, so for a matrix that is not symmetric it returns a^T x.
Eigen::VectorXd symmetric_product(const SparseMatrix& a, const Eigen::VectorXd& x);

// The paper's fixed-point iteration (3.11): theta^{K+1} = theta^K + (rhs - A theta^K) / c, i.e.
// theta^{K+1} = theta^n + [dt phi Q(theta^K) + dt (1 - phi) Q(theta^n) + dH] / c. It contracts only
// while the spectral radius of dt phi c^{-1} (L + W) is below 1, so it watches the size of its
// updates and throws RunError on divergence, stagnation or the iteration cap: it never returns an
// unconverged field. Converged when max|update| <= tolerance * max|theta| (the thermal model
// solves for a step's change, so the tolerance is relative to what the step changes).
SolveStats fixed_point_solve(const SparseMatrix& a, const Eigen::VectorXd& c,
                             const Eigen::VectorXd& rhs, Eigen::VectorXd& theta, double tolerance,
                             int max_iterations, double contraction_estimate);

// Conjugate gradients with the diagonal (Jacobi) preconditioner, started from theta.
// Converged when |rhs - A theta| <= tolerance |rhs| (theta = 0 when rhs = 0); RunError otherwise.
SolveStats cg_solve(const SparseMatrix& a, const Eigen::VectorXd& rhs, Eigen::VectorXd& theta,
                    double tolerance, int max_iterations);

// thermal.solver = "auto"'s pick for a system of `rows` rows whose contraction estimate (dt phi
// times the largest row sum of L + W over c) is `contraction`: "fixed-point" up to 0.1 (each
// iteration gains a factor 10 or more), "cg" while the system is well conditioned (its iterations
// grow like the square root of the estimate: ~4 sqrt of it per solve, measured), "direct" for
// stiffer steps, where iterative methods crawl. The factorisation's cost grows much faster than
// its rows (a bed of touching spheres, K = 100: 0.1, 1.2 and 22 s per factorisation at 1e5, 3e5
// and 1e6 rows, against CG's 0.07, 0.3 and 2.2 s), CG's as rows times the root of the estimate:
// past kAutoSmallRows rows the CG bound grows as rows^2, but only as far as CG's expected
// iterations stay within half of max_iterations (a CG that fails under "auto" is followed by the
// factorisation, so a wrong pick costs time, never a result).
inline constexpr double kAutoSmallRows = 65536;
inline constexpr double kAutoCgBound = 100;  // the contraction CG takes up to at kAutoSmallRows
const char* auto_solver(double contraction, Eigen::Index rows, int max_iterations);

// Sparse LDL^T that keeps the symbolic analysis while the pattern version is unchanged, and the
// numeric factors while the matrix values are unchanged too (a fixed step without phase change).
class DirectSolver {
 public:
  void solve(const SparseMatrix& a, std::uint64_t pattern_version, const Eigen::VectorXd& rhs,
             Eigen::VectorXd& theta);
  bool symbolic_reused() const { return symbolic_reused_; }
  bool factors_reused() const { return factors_reused_; }
  void forget() { analysed_ = false; }

 private:
  Eigen::SimplicialLDLT<SparseMatrix> ldlt_;
  bool analysed_ = false;
  std::uint64_t pattern_version_ = 0;
  std::vector<double> factored_values_;
  bool symbolic_reused_ = false;
  bool factors_reused_ = false;
};

}  // namespace beampack
