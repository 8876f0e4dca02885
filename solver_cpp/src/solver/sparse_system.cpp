// Global sparse system: see sparse_system.hpp.
#include "solver/sparse_system.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace calfit {
namespace {

// CHOLMOD (SuiteSparse 5) runs the copy and zeroing loops of its supernodal factorization on a fixed 4 OpenMP
// threads, whatever --threads says: on 2 cores the wake-ups and waits cost more than the loops (the 22.5k-DOF calf
// of benchmarks/engine.py: 49 ms per factorization against 25 ms serial; 0.68 s against 0.53 s at 200k DOF). The
// parallelism that pays in a factorization is the BLAS's, which --threads sets. While a solve runs, OpenMP regions
// are made inactive (max-active-levels 0: every region one thread) and restored after, so that the engine's own
// parallel loops keep their threads. Those loops only copy, so the digits do not depend on it.
class SerialOpenMpRegions {
public:
#ifdef _OPENMP
  SerialOpenMpRegions() : saved_(omp_get_max_active_levels()) { omp_set_max_active_levels(0); }
  ~SerialOpenMpRegions() { omp_set_max_active_levels(saved_); }

private:
  int saved_;
#endif
public:
  SerialOpenMpRegions(const SerialOpenMpRegions&) = delete;
  SerialOpenMpRegions& operator=(const SerialOpenMpRegions&) = delete;
};

}  // namespace

SparseSystem::SparseSystem(const std::vector<std::vector<int>>& element_dofs, const std::vector<char>& free,
                           bool saddle_point, const std::vector<std::vector<int>>& appended_dofs)
    : equation_(free.size(), -1), saddle_point_(saddle_point) {
  int n = 0;
  for (std::size_t d = 0; d < free.size(); ++d)
    if (free[d]) equation_[d] = n++;
  const std::size_t n_blocks = element_dofs.size() + appended_dofs.size();
  auto block = [&](std::size_t b) -> const std::vector<int>& {
    return b < element_dofs.size() ? element_dofs[b] : appended_dofs[b - element_dofs.size()];
  };

  // Flat arrays throughout (a vector per column or per element, and a sort and a binary search per entry, took
  // 23 ms of a 0.23 s run on the 22.5k-DOF calf, more than its assembly). The blocks' equations, -1 prescribed:
  std::vector<int> block_equations;
  block_start_.assign(n_blocks + 1, 0);
  position_start_.assign(n_blocks + 1, 0);
  for (std::size_t b = 0; b < n_blocks; ++b) {
    const std::vector<int>& dofs = block(b);
    for (int d : dofs) block_equations.push_back(equation_[d]);
    block_start_[b + 1] = static_cast<int>(block_equations.size());
    position_start_[b + 1] = position_start_[b] + static_cast<std::size_t>(dofs.size() * dofs.size());
  }
  // Which blocks each equation belongs to, with its local index there (counted, then filled).
  std::vector<int> incidence_start(static_cast<std::size_t>(n) + 1, 0);
  for (int r : block_equations)
    if (r >= 0) ++incidence_start[static_cast<std::size_t>(r) + 1];
  for (int c = 0; c < n; ++c) incidence_start[c + 1] += incidence_start[c];
  std::vector<std::pair<int, int>> incidence(static_cast<std::size_t>(incidence_start[n]));
  {
    std::vector<int> next(incidence_start.begin(), incidence_start.end() - 1);
    for (std::size_t b = 0; b < n_blocks; ++b)
      for (int k = block_start_[b]; k < block_start_[b + 1]; ++k)
        if (block_equations[k] >= 0) incidence[next[block_equations[k]]++] = {static_cast<int>(b), k - block_start_[b]};
  }

  // The rows of each column, unsorted: the equations of the blocks that hold the column's, each once (a marker
  // per row). The pattern is symmetric, so transposing it (a counting sort) lists every column's rows in
  // increasing order: compressed-column storage as CHOLMOD and Eigen expect.
  std::vector<int> rows, column_start(static_cast<std::size_t>(n) + 1, 0), marker(static_cast<std::size_t>(n), -1);
  rows.reserve(static_cast<std::size_t>(incidence_start[n]) * 8);
  for (int c = 0; c < n; ++c) {
    for (int q = incidence_start[c]; q < incidence_start[c + 1]; ++q) {
      const int b = incidence[q].first;
      for (int k = block_start_[b]; k < block_start_[b + 1]; ++k) {
        const int r = block_equations[k];
        if (r >= 0 && marker[r] != c) {
          marker[r] = c;
          rows.push_back(r);
        }
      }
    }
    column_start[c + 1] = static_cast<int>(rows.size());
  }
  const std::size_t nnz = rows.size();
  matrix_.resize(n, n);
  matrix_.resizeNonZeros(static_cast<Eigen::Index>(nnz));
  int* outer = matrix_.outerIndexPtr();
  int* inner = matrix_.innerIndexPtr();
  std::copy(column_start.begin(), column_start.end(), outer);  // symmetric: the transpose has the same column counts
  {
    std::vector<int> next(column_start.begin(), column_start.end() - 1);
    for (int c = 0; c < n; ++c)
      for (int p = column_start[c]; p < column_start[c + 1]; ++p) inner[next[rows[p]]++] = c;
  }
  std::fill(matrix_.valuePtr(), matrix_.valuePtr() + nnz, 0.0);

  // Each block's m x m entries into the value array (-1 where a dof is prescribed), column by column: the rows of
  // column c are looked up in a table of where each sits in that column.
  positions_.assign(position_start_[n_blocks], -1);
  std::vector<int>& where = marker;
  for (int c = 0; c < n; ++c) {
    for (int p = outer[c]; p < outer[c + 1]; ++p) where[inner[p]] = p;
    for (int q = incidence_start[c]; q < incidence_start[c + 1]; ++q) {
      const auto [b, j] = incidence[q];
      const int m = block_start_[b + 1] - block_start_[b];
      int* pos = positions_.data() + position_start_[b] + static_cast<std::size_t>(m) * j;
      for (int i = 0; i < m; ++i) {
        const int r = block_equations[block_start_[b] + i];
        if (r >= 0) pos[i] = where[r];
      }
    }
  }
  // The pattern is symmetric: column r holds row c where column c holds row r, and walking the columns in order
  // meets the entries (c, r) of column r in increasing c, so a cursor per column finds every transpose in O(nnz).
  transpose_position_.resize(nnz);
  std::vector<int> cursor(outer, outer + n);
  for (int c = 0; c < n; ++c)
    for (int p = outer[c]; p < outer[c + 1]; ++p) transpose_position_[p] = cursor[inner[p]]++;
}

int SparseSystem::find(int row, int column) const {
  const int* inner = matrix_.innerIndexPtr();
  const int* first = inner + matrix_.outerIndexPtr()[column];
  const int* last = inner + matrix_.outerIndexPtr()[column + 1];
  const int* at = std::lower_bound(first, last, row);
  return at != last && *at == row ? static_cast<int>(at - inner) : -1;
}

bool SparseSystem::holds(const std::vector<int>& dofs) const {
  for (int c : dofs) {
    if (equation_[c] < 0) continue;
    for (int r : dofs)
      if (equation_[r] >= 0 && find(equation_[r], equation_[c]) < 0) return false;
  }
  return true;
}

void SparseSystem::add_coupled(const std::vector<int>& dofs, const Eigen::MatrixXd& K) {
  double* values = matrix_.valuePtr();
  const auto m = static_cast<Eigen::Index>(dofs.size());
  for (Eigen::Index j = 0; j < m; ++j) {
    const int c = equation_[dofs[static_cast<std::size_t>(j)]];
    if (c < 0) continue;
    for (Eigen::Index i = 0; i < m; ++i) {
      const int r = equation_[dofs[static_cast<std::size_t>(i)]];
      if (r < 0) continue;
      const int p = find(r, c);
      if (p >= 0) values[p] += K(i, j);  // held: the caller checked with holds()
    }
  }
}

void SparseSystem::set_zero() { std::fill(matrix_.valuePtr(), matrix_.valuePtr() + matrix_.nonZeros(), 0.0); }

bool SparseSystem::symmetric() const {
  const double* v = matrix_.valuePtr();
  double largest = 0.0, asymmetry = 0.0;
  for (std::size_t p = 0; p < transpose_position_.size(); ++p) {
    largest = std::max(largest, std::abs(v[p]));
    asymmetry = std::max(asymmetry, std::abs(v[p] - v[transpose_position_[p]]));
  }
  return asymmetry <= 1e-12 * largest;
}

bool SparseSystem::finite() const {
  return Eigen::Map<const Eigen::VectorXd>(matrix_.valuePtr(), matrix_.nonZeros()).allFinite();
}

bool SparseSystem::became_indefinite() {
  if (!indefinite_ || reported_indefinite_) return false;
  reported_indefinite_ = true;
  return true;
}

bool SparseSystem::accurate(const Eigen::VectorXd& b, const Eigen::VectorXd& x) const {
  return x.allFinite() && (matrix_ * x - b).norm() <= 1e-8 * std::max(b.norm(), 1e-300);
}

double SparseSystem::ldlt_flops() {
  if (!ldlt_) {
    ldlt_ = std::make_unique<Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower>>();
    ldlt_->setMode(Eigen::CholmodLDLt);
    ldlt_->cholmod().print = 0;  // a failure is handled here, by UMFPACK
    ldlt_->analyzePattern(matrix_);
  }
  return ldlt_->cholmod().fl;
}

bool SparseSystem::solve_ldlt(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  ldlt_flops();  // analyses the pattern once
  ldlt_->factorize(matrix_);
  if (ldlt_->info() != Eigen::Success) return false;
  x = ldlt_->solve(b);
  solver_name_ = "cholmod-ldlt";
  factor_ = Factor::Ldlt;
  return ldlt_->info() == Eigen::Success && accurate(b, x);
}

bool SparseSystem::factorize_cholesky(const Eigen::SparseMatrix<double>& matrix) {
  if (!cholesky_) {
    cholesky_ = std::make_unique<Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower>>();
    cholesky_->cholmod().print = 0;  // a lost definiteness is handled by UMFPACK, not printed
    cholesky_->analyzePattern(matrix);  // the symmetric part has the matrix's (symmetric) pattern
  }
  cholesky_->factorize(matrix);
  return cholesky_->info() == Eigen::Success;
}

template <typename Rhs>
typename Rhs::PlainObject SparseSystem::apply_factor(const Eigen::MatrixBase<Rhs>& B) const {
  switch (factor_) {
    case Factor::Cholesky:
    case Factor::SymmetricPart: return cholesky_->solve(B);
    case Factor::Ldlt: return ldlt_->solve(B);
    // UMFPACK solves one column at a time, unrefined (solve_lu says why): with the sensitivities of many parameters
    // along a path of friction (a diagnosis's 145 columns at each of 23 increments) its own refinement was most of
    // the run (a third in the residuals alone). solve_refined refines the block where it needs to.
    case Factor::Lu: return lu_->solve(B);
    case Factor::None: break;
  }
  return Rhs::PlainObject::Constant(B.rows(), B.cols(), std::numeric_limits<double>::quiet_NaN());
}

// Solves K x = b by GMRES right-preconditioned with the factorization F held (Saad, Iterative Methods for Sparse
// Linear Systems, 2nd ed., Algorithm 9.5): F is the Cholesky factor of K's symmetric part S when K = S + W is
// unsymmetric (follower loads), or the Cholesky or LU factorization of an earlier Newton iterate's tangent, or of K
// itself (a fresh LU, whose first solve usually meets the tolerance outright). The Krylov space of K F^-1, whose eigenvalues
// cluster about 1 when K - F is small, reaches a relative residual `tolerance` in a few back-substitutions (7 to
// kExactSolve on the calf under a non-uniform follower pressure); with right preconditioning the residual GMRES
// minimizes is the true one. kExactSolve = 1e-10 of |b| stays above the round-off of K x (1e-12 was not reachable
// when b was a small late correction). False when that takes more than `max_iterations`.
bool SparseSystem::iterate_on_factor(const Eigen::VectorXd& b, Eigen::VectorXd& x, int max_iterations,
                                     int* iterations, double tolerance) const {
  const int n = size();
  const double target = tolerance * std::max(b.norm(), 1e-300);
  const int m = max_iterations;
  // The preconditioned directions F^-1 v_k are kept (the columns of `directions`, touched only as GMRES reaches
  // them): the update x0 + F^-1 V y is then x0 + Z y, without one more back-substitution (3 ms of the 22.5k-DOF
  // calf's, each), at the price of n doubles per step taken.
  Eigen::MatrixXd basis(n, m + 1), directions(n, m);
  Eigen::MatrixXd hessenberg = Eigen::MatrixXd::Zero(m + 1, m);
  Eigen::VectorXd g = Eigen::VectorXd::Zero(m + 1), cosines(m), sines(m);
  x = apply_factor(b);
  Eigen::VectorXd r = b - matrix_ * x;
  const double beta = r.norm();
  if (iterations) *iterations = 0;
  if (!std::isfinite(beta)) return false;
  if (beta <= target) return true;
  basis.col(0) = r / beta;
  g(0) = beta;
  int k = 0;
  for (; k < m; ++k) {
    directions.col(k) = apply_factor(basis.col(k));
    Eigen::VectorXd w = matrix_ * directions.col(k);
    for (int i = 0; i <= k; ++i) {  // modified Gram-Schmidt
      hessenberg(i, k) = basis.col(i).dot(w);
      w -= hessenberg(i, k) * basis.col(i);
    }
    hessenberg(k + 1, k) = w.norm();
    if (!std::isfinite(hessenberg(k + 1, k))) return false;
    if (hessenberg(k + 1, k) > 0.0) basis.col(k + 1) = w / hessenberg(k + 1, k);
    for (int i = 0; i < k; ++i) {  // the earlier Givens rotations, then this column's own
      const double upper = cosines(i) * hessenberg(i, k) + sines(i) * hessenberg(i + 1, k);
      hessenberg(i + 1, k) = -sines(i) * hessenberg(i, k) + cosines(i) * hessenberg(i + 1, k);
      hessenberg(i, k) = upper;
    }
    const double radius = std::hypot(hessenberg(k, k), hessenberg(k + 1, k));
    cosines(k) = hessenberg(k, k) / radius;
    sines(k) = hessenberg(k + 1, k) / radius;
    hessenberg(k, k) = radius;
    hessenberg(k + 1, k) = 0.0;
    g(k + 1) = -sines(k) * g(k);
    g(k) *= cosines(k);
    if (std::abs(g(k + 1)) <= target || hessenberg.coeff(k, k) == 0.0) {
      ++k;
      break;
    }
  }
  if (iterations) *iterations = k;
  const Eigen::VectorXd y =
      hessenberg.topLeftCorner(k, k).triangularView<Eigen::Upper>().solve(g.head(k));
  x += directions.leftCols(k) * y;
  return x.allFinite() && (b - matrix_ * x).norm() <= target;
}

bool SparseSystem::solve_split(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance) {
  constexpr int kMaxSplitIterations = 30;
  if (symmetric_part_.nonZeros() != matrix_.nonZeros()) symmetric_part_ = matrix_;
  const double* v = matrix_.valuePtr();
  double* s = symmetric_part_.valuePtr();
  for (std::size_t p = 0; p < transpose_position_.size(); ++p) s[p] = 0.5 * (v[p] + v[transpose_position_[p]]);
  if (!factorize_cholesky(symmetric_part_)) return false;
  factor_ = Factor::SymmetricPart;
  solver_name_ = "cholmod-split";
  int iterations = 0;
  const bool solved = iterate_on_factor(b, x, kMaxSplitIterations, &iterations, tolerance);
  krylov_steps_ += solved ? iterations : kMaxSplitIterations;
  return solved;
}

bool SparseSystem::solve_lu(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance) {
  if (!lu_) {
    lu_ = std::make_unique<Eigen::UmfPackLU<Eigen::SparseMatrix<double>>>();
    // The pattern is symmetric by construction (element and contact blocks are square), the values nearly so
    // (friction's and the follower pressure's skew parts are small): UMFPACK's symmetric strategy (AMD on A + A',
    // diagonal pivots preferred, threshold partial pivoting kept). Its automatic choice reads the hybrid elements'
    // zero pressure diagonals (10.5 % of the unknowns of the CPE6H leg under the band) as a sign of an unsymmetric
    // matrix and orders A^T A by COLAMD instead: on that leg with friction (20.5k unknowns) 6.4 times the flops
    // (2.25e9 against 3.5e8) and 3.3 times the factor's entries, and the run took twice the CPU time.
    lu_->umfpackControl()(UMFPACK_STRATEGY) = UMFPACK_STRATEGY_SYMMETRIC;
    // No iterative refinement inside UMFPACK: each of its steps (two by default) costs a residual and a solve of
    // its own, which made a solve 6 times dearer (15 ms against 2.5 on the garment deck's 9.6k unknowns) and a
    // sixth of the garment's run with friction. GMRES on the factor (iterate_on_factor) refines where the
    // tolerance asks, checked on the true residual.
    lu_->umfpackControl()(UMFPACK_IRSTEP) = 0;
    lu_->analyzePattern(matrix_);
  }
  lu_->factorize(matrix_);
  if (lu_->info() != Eigen::Success) return false;
  solver_name_ = "umfpack";
  factor_ = Factor::Lu;
  constexpr int kMaxRefinements = 30;
  int iterations = 0;
  const bool solved = iterate_on_factor(b, x, kMaxRefinements, &iterations, tolerance);
  krylov_steps_ += iterations;
  return solved;
}

bool SparseSystem::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance) {
  const SerialOpenMpRegions serial;
  if (size() == 0) {
    x.resize(0);
    return true;
  }
  const bool is_symmetric = symmetric();
  const bool cholesky = !indefinite_ && (is_symmetric || split_skew_) &&
                        (factor_ == Factor::Cholesky || factor_ == Factor::SymmetricPart);
  if (!saddle_point_ && (cholesky || factor_ == Factor::Lu) && reuse_pays()) {
    // Newton's tangent changes little from one iteration to the next: an earlier factor iterated to the current
    // matrix costs a few back-substitutions instead of a factorization
    const int max_iterations = factor_ == Factor::Lu ? kMaxLuReuseIterations : 16;
    int iterations = 0;
    const bool reused = iterate_on_factor(b, x, max_iterations, &iterations, tolerance);
    const int steps = reused ? iterations : max_iterations;   // a failure counted at its limit
    record_reuse(steps);
    krylov_steps_ += steps;
    if (reused) {
      ++reused_factorizations_;
      stale_factor_ = true;
      return true;
    }
  } else if (factor_ == Factor::Lu) {
    lu_reuse_steps_ *= kLuReuseForgetting;  // not tried: the record fades, and an attempt is made again
  }
  return solve_fresh(b, x, is_symmetric, tolerance);
}

void SparseSystem::record_reuse(int steps) {
  if (factor_ != Factor::Lu) {
    ++reuse_attempts_;
    reuse_iterations_ += steps;
    return;
  }
  lu_reuse_steps_ = lu_reuse_attempts_++ == 0 ? steps : 0.7 * lu_reuse_steps_ + 0.3 * steps;
}

void SparseSystem::inherit_solver_choices(const SparseSystem& earlier) {
  split_skew_ = earlier.split_skew_;
  split_failures_ = earlier.split_failures_;
  reuse_attempts_ = earlier.reuse_attempts_;
  reuse_iterations_ = earlier.reuse_iterations_;
  lu_reuse_attempts_ = earlier.lu_reuse_attempts_;
  lu_reuse_steps_ = earlier.lu_reuse_steps_;
}

// Reusing a factor pays when its GMRES iterations, failures counted at their limit, cost less on average than a
// factorization. The costs are counted, not timed, so that the solver's choices, and with them the last digits
// of a result, do not depend on the machine's load: an iteration is two triangular solves and a product with the
// matrix, 4 nnz(L) + 2 nnz(K) flops, which run at about kSolveRateRatio times the slower rate of a supernodal
// factorization's fl flops, whose BLAS 3 kernels reuse the cache (measured on the 22.5k-DOF calf of
// benchmarks/engine.py: fl = 1.7e8 in 60 ms, an iteration 6.8e6 flops in 3.6 ms: 2.8 and 1.9 GFlop/s).
//
// UMFPACK reports no flop count through Eigen's interface; there a GMRES step (a solve with L and U, a product with
// the matrix) is counted as kLuStepsPerFactorization-th of a factorization, the ratio measured on the garment decks'
// matrices (9.6k unknowns: LU 41-67 ms, a step 2.8-3.3 ms; 22k: 121-167 ms against 7-10 ms), and an earlier LU is
// reused while its recent attempts took less than half that: a moving average of their steps (weight 0.3 on the
// last), which fades by kLuReuseForgetting at each factorization taken without an attempt. Where reuse did not pay
// for a while (a garment band wrapping onto the skin) it is tried again after a few factorizations, and pays again
// once the increments settle (the release with friction in 200 increments: 3-4 Newton iterations each).
bool SparseSystem::reuse_pays() const {
  constexpr double kSolveRateRatio = 1.5;
  constexpr double kLuStepsPerFactorization = 14.0;
  if (factor_ == Factor::Lu) return lu_reuse_attempts_ < 2 || lu_reuse_steps_ < 0.5 * kLuStepsPerFactorization;
  if (reuse_attempts_ < 2 || !cholesky_) return true;
  const double average = static_cast<double>(reuse_iterations_) / reuse_attempts_;
  const cholmod_common& common = cholesky_->cholmod();
  const double per_iteration = kSolveRateRatio * (4.0 * common.lnz + 2.0 * static_cast<double>(matrix_.nonZeros()));
  return average * per_iteration < common.fl;
}

bool SparseSystem::solve_fresh(const Eigen::VectorXd& b, Eigen::VectorXd& x, bool is_symmetric, double tolerance) {
  stale_factor_ = false;   // whatever it factorizes is the current matrix
  if (!saddle_point_ && is_symmetric && !indefinite_) {
    if (factorize_cholesky(matrix_)) {
      x = cholesky_->solve(b);
      solver_name_ = "cholmod";
      factor_ = Factor::Cholesky;
      if (cholesky_->info() == Eigen::Success && x.allFinite()) return true;
    }
    indefinite_ = true;
  }
  if (!saddle_point_ && !is_symmetric && !indefinite_ && split_skew_) {
    // A symmetric part that is not definite at one iterate may be again at the next (the garment band's first
    // touch without friction: once in 30 iterations, where giving the split up made every later solve an LU,
    // four times a Cholesky factorization's cost); with friction it stays indefinite. The split is given up after
    // kMaxSplitFailures failures in a row.
    constexpr int kMaxSplitFailures = 2;
    if (solve_split(b, x, tolerance)) {
      split_failures_ = 0;
      return true;
    }
    split_skew_ = ++split_failures_ < kMaxSplitFailures;
  }
  if (saddle_point_ && is_symmetric && choice_ != Choice::Lu) {
    // CHOLMOD's LDL^T (simplicial, no pivoting: valid for the quasi-definite D1 > 0 systems, and checked by its
    // residual) took half the time of UMFPACK's LU at 1.5e7 flops and 85 % at 3.7e8 (CPE6H leg slices of 4.6k
    // and 25k unknowns, analysis included; UMFPACK then ran its automatic strategy, with the symmetric one of
    // solve_lu the two are level at 25k), the gap closing as fl^0.17: past kLdltFlopLimit LU is used. Counted,
    // not timed, so that the choice, and with it the last digits of a result, does not depend on the load.
    constexpr double kLdltFlopLimit = 1e9;
    if ((choice_ == Choice::Ldlt || ldlt_flops() <= kLdltFlopLimit) && solve_ldlt(b, x)) {
      choice_ = Choice::Ldlt;
      return true;
    }
    choice_ = Choice::Lu;  // a zero pivot (D1 = 0, an instability), or too large a factor
  }
  return solve_lu(b, x, tolerance);
}

bool SparseSystem::solve_factored(const Eigen::VectorXd& b, Eigen::VectorXd& x) const {
  const SerialOpenMpRegions serial;
  if (factor_ == Factor::None) return false;
  // a Cholesky factor may be of the symmetric part, or a factor of an earlier matrix than the one held (Newton
  // iterations reuse it): GMRES on it solves the matrix held, as a fresh factorization would
  if ((factor_ == Factor::Cholesky || factor_ == Factor::SymmetricPart || factor_ == Factor::Lu) &&
      iterate_on_factor(b, x, 30))
    return true;
  x = apply_factor(b);
  return x.allFinite();
}

bool SparseSystem::solve_refined(const Eigen::MatrixXd& B, Eigen::MatrixXd& X, double tolerance) {
  const SerialOpenMpRegions serial;
  if (size() == 0 || B.cols() == 0) {
    X.setZero(size(), B.cols());
    return true;
  }
  const Eigen::RowVectorXd norms = B.colwise().norm().cwiseMax(1e-300);
  auto relative_residual = [&] { return ((B - matrix_ * X).colwise().norm().array() / norms.array()).maxCoeff(); };
  for (int attempt = 0; attempt < 2; ++attempt) {
    // a factor that Newton's last solves reused is several iterations old: GMRES on it would take many steps for
    // each of many columns (the diagnosis asks for dozens), where one factorization of the current matrix leaves
    // one or two (the identification and diagnosis of the leg with a hidden drainage took twice as long without)
    if (factor_ == Factor::None || attempt == 1 || (stale_factor_ && B.cols() > 1)) {
      Eigen::VectorXd first;
      if (!solve_fresh(B.col(0), first, symmetric())) return false;  // factorizes the current matrix
    }
    if (factor_ == Factor::Cholesky || factor_ == Factor::SymmetricPart) {  // GMRES on the factor, per column
      X.resize(size(), B.cols());
      bool solved = true;
      for (int j = 0; j < B.cols() && solved; ++j) {
        Eigen::VectorXd column;
        solved = iterate_on_factor(B.col(j), column, 30);
        X.col(j) = column;
      }
      if (solved && relative_residual() <= tolerance) return true;
      continue;
    }
    X = apply_factor(B);
    double previous = std::numeric_limits<double>::infinity();
    for (int it = 0; it < 10 && X.allFinite(); ++it) {
      const double r = relative_residual();
      if (r <= tolerance) return true;
      if (!(r < 0.5 * previous)) break;  // stalled: factorize the current matrix
      previous = r;
      X += apply_factor(Eigen::MatrixXd(B - matrix_ * X));
    }
  }
  return false;
}

}  // namespace calfit
