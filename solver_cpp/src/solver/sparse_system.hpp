// The global tangent system of calfit-fe: numbering of the free degrees of freedom,
// a compressed-column matrix whose pattern is built once from the element
// connectivity, per-element scatter maps into its value array (so assembly is a
// plain indexed add), and the direct solve: CHOLMOD supernodal LL^T when the
// assembled tangent is symmetric positive definite. Follower loads make it
// unsymmetric, K = S + W with S its symmetric part and W the small skew part of the
// pressure's load stiffness: K x = b is then solved by iterating on the Cholesky
// factor of S, x <- x + S^-1 (b - K x), which converges at the rate |S^-1 W| (a few
// hundredths on a calf under a garment) to the accuracy of a direct solve, at a
// third of the cost of an LU of K. UMFPACK LU takes over when S is not positive
// definite or the iterations are slow (a loss of definiteness near an instability
// too, detected once and then remembered, with the libraries' own messages silenced); an
// LU of an earlier Newton iterate's matrix is iterated on by GMRES as a Cholesky factor is. The
// saddle-point systems of the hybrid elements are symmetric indefinite: CHOLMOD's LDL^T
// (no pivoting: valid for the quasi-definite D1 > 0 case, and checked by its residual)
// solves them up to a factorization cost where UMFPACK's LU is faster, LU past it or when
// LDL^T fails. Every choice is made on counts (flops, GMRES steps), never on timings, so
// that a run gives the same digits on a busy machine as on an idle one.
#pragma once

#include <Eigen/Sparse>
#include <Eigen/CholmodSupport>
#include <Eigen/UmfPackSupport>
#include <memory>
#include <string>
#include <vector>

namespace calfit {

class SparseSystem {
public:
  // element_dofs[e]: global dofs of element e in its local order; free[dof]: unknown or prescribed.
  // appended_dofs: further elements (contact), numbered after those of element_dofs in add().
  SparseSystem(const std::vector<std::vector<int>>& element_dofs, const std::vector<char>& free,
               bool saddle_point = false, const std::vector<std::vector<int>>& appended_dofs = {});

  int size() const { return static_cast<int>(matrix_.rows()); }
  int equation(int dof) const { return equation_[dof]; }  // -1 when prescribed
  void set_zero();
  // Adds the block K (local dofs `local` of element e, rows and columns) to the matrix.
  template <typename Block>
  void add(int element, const Block& K, const int* local = nullptr, int n_local = -1);
  // Whether the pattern holds every coupling between the free ones of `dofs` (a contact element's), and adds
  // such a block K (rows and columns in the order of `dofs`) by looking its entries up in the pattern: contact
  // elements come and go from one Newton iterate to the next, the pattern stays while it holds them.
  bool holds(const std::vector<int>& dofs) const;
  void add_coupled(const std::vector<int>& dofs, const Eigen::MatrixXd& K);

  // Solves A x = b to a relative residual |b - A x| <= tolerance |b| (a direct solve's when it factorizes A):
  // with the factorization of an earlier matrix when GMRES on it converges in a few steps, otherwise by
  // factorizing the current matrix (its symmetric part and GMRES when it is unsymmetric: see the file's text).
  // Returns false when singular.
  bool solve(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance = kExactSolve);
  static constexpr double kExactSolve = 1e-10;  // as good as a direct solve for Newton (see iterate_on_factor)
  static constexpr int kMaxLuReuseIterations = 12;  // GMRES steps on an earlier LU before factorizing (reuse_pays)
  static constexpr double kLuReuseForgetting = 0.8;
  // Solves A X = B for every column of B, to a relative residual |B - A X| / |B| <=
  // tolerance per column, with the factorization F of the last solve(), possibly of an
  // earlier matrix (Newton's previous iterate), against the current matrix: GMRES on a
  // Cholesky factor (as solve()), iterative refinement X <- X + F^-1 (B - A X) on an LU or
  // LDL^T one (Golub & Van Loan, Matrix Computations, 4th ed., sec. 3.5.3), which
  // converges at the rate |I - F^-1 A|, tiny near a converged Newton state. Factorizes the
  // current matrix when there is no factorization yet or that fails. Returns false when singular.
  bool solve_refined(const Eigen::MatrixXd& B, Eigen::MatrixXd& X, double tolerance);
  // Solves with the factorization of the last solve() (of an earlier matrix, possibly), without factorizing.
  // Returns false when there is none or the result is not finite.
  bool solve_factored(const Eigen::VectorXd& b, Eigen::VectorXd& x) const;
  bool factorized() const { return factor_ != Factor::None; }
  const std::string& solver_name() const { return solver_name_; }
  // Solves that iterated on an earlier factorization instead of factorizing the current matrix.
  int reused_factorizations() const { return reused_factorizations_; }
  int krylov_steps() const { return krylov_steps_; }  // GMRES steps of every solve() so far
  // Takes over what an earlier system of the same model learned (contact changes the pattern, so the system is
  // rebuilt): whether the symmetric part failed, and the GMRES counts that say whether reusing a factor pays.
  void inherit_solver_choices(const SparseSystem& earlier);
  bool symmetric() const;
  // Whether every entry of the matrix is finite (an overflowed element must not reach a factorization).
  bool finite() const;
  // True once, right after the solve in which a symmetric tangent turned out not to be positive definite: from
  // then on this system skips the Cholesky attempt and solves with LU (an instability, a compressed structure
  // whose geometric stiffness went negative), without a library message at every iteration.
  bool became_indefinite();

private:
  std::vector<int> equation_;
  std::vector<int> block_start_;              // element e's dofs are block_start_[e] .. block_start_[e + 1] - 1
  std::vector<std::size_t> position_start_;  // element e's m x m entries into valuePtr, -1 when prescribed, ...
  std::vector<int> positions_;               // ... are positions_[position_start_[e] ..] (column-major)
  std::vector<int> transpose_position_;      // entry (r, c) -> entry (c, r)
  Eigen::SparseMatrix<double> matrix_;
  Eigen::SparseMatrix<double> symmetric_part_;  // (K + K^T) / 2, for unsymmetric K
  std::unique_ptr<Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower>> cholesky_;
  std::unique_ptr<Eigen::UmfPackLU<Eigen::SparseMatrix<double>>> lu_;
  std::unique_ptr<Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower>> ldlt_;
  enum class Choice { Undecided, Ldlt, Lu };
  enum class Factor { None, Cholesky, Ldlt, Lu, SymmetricPart };  // the factorization the last solve used
  bool saddle_point_ = false;
  bool split_skew_ = true;  // off once the symmetric part failed twice in a row (not definite, or iterations too slow)
  int split_failures_ = 0;  // failures of the split in a row
  int reused_factorizations_ = 0;
  int krylov_steps_ = 0;
  bool stale_factor_ = false;  // the last solve() iterated on the factor of an earlier matrix
  int reuse_attempts_ = 0, reuse_iterations_ = 0;  // attempts to iterate on an earlier Cholesky factor, their steps
  // Attempts on an earlier LU and their GMRES steps, a moving average that forgets (see reuse_pays)
  int lu_reuse_attempts_ = 0;
  double lu_reuse_steps_ = 0.0;
  bool indefinite_ = false, reported_indefinite_ = false;
  Choice choice_ = Choice::Undecided;
  Factor factor_ = Factor::None;
  std::string solver_name_ = "none";

  bool solve_ldlt(const Eigen::VectorXd& b, Eigen::VectorXd& x);
  double ldlt_flops();  // flops of the LDL^T factorization (analysing the pattern the first time)
  bool solve_lu(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance);
  bool solve_split(const Eigen::VectorXd& b, Eigen::VectorXd& x, double tolerance);
  int find(int row, int column) const;  // position of entry (row, column) in the value array, -1 if not held
  // F^-1 B with the factorization held, unrefined: a vector (GMRES's steps) or a block of columns (sensitivities)
  template <typename Rhs>
  typename Rhs::PlainObject apply_factor(const Eigen::MatrixBase<Rhs>& B) const;
  bool solve_fresh(const Eigen::VectorXd& b, Eigen::VectorXd& x, bool is_symmetric, double tolerance = kExactSolve);
  bool reuse_pays() const;
  void record_reuse(int steps);  // an attempt to iterate on an earlier factor, failures counted at their limit
  // GMRES on the factorization held (see the .cpp); `iterations` (if given) receives the steps it took.
  bool iterate_on_factor(const Eigen::VectorXd& b, Eigen::VectorXd& x, int max_iterations,
                         int* iterations = nullptr, double tolerance = kExactSolve) const;
  bool factorize_cholesky(const Eigen::SparseMatrix<double>& matrix);
  bool accurate(const Eigen::VectorXd& b, const Eigen::VectorXd& x) const;
};

template <typename Block>
void SparseSystem::add(int element, const Block& K, const int* local, int n_local) {
  const int* pos = positions_.data() + position_start_[element];
  const int m = block_start_[element + 1] - block_start_[element];
  double* values = matrix_.valuePtr();
  if (!local) {
    for (int j = 0; j < m; ++j)
      for (int i = 0; i < m; ++i) {
        const int p = pos[i + m * j];
        if (p >= 0) values[p] += K(i, j);
      }
    return;
  }
  for (int j = 0; j < n_local; ++j)
    for (int i = 0; i < n_local; ++i) {
      const int p = pos[local[i] + m * local[j]];
      if (p >= 0) values[p] += K(i, j);
    }
}

}  // namespace calfit
