// The global tangent system of calfit-fe: numbering of the free degrees of freedom,
// a compressed-column matrix whose pattern is built once from the element
// connectivity, per-element scatter maps into its value array (so assembly is a
// plain indexed add), and the direct solve: CHOLMOD supernodal LL^T when the
// assembled tangent is symmetric positive definite, UMFPACK LU otherwise (follower
// loads make it unsymmetric; a loss of definiteness near an instability too, detected
// once and then remembered, with the libraries' own messages silenced). The
// saddle-point systems of the hybrid elements are symmetric indefinite: on the first
// solve both CHOLMOD's LDL^T (no pivoting: valid for the quasi-definite D1 > 0 case,
// and checked by its residual) and UMFPACK are timed, and the faster valid one is kept.
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
  SparseSystem(const std::vector<std::vector<int>>& element_dofs, const std::vector<char>& free,
               bool saddle_point = false);

  int size() const { return static_cast<int>(matrix_.rows()); }
  int equation(int dof) const { return equation_[dof]; }  // -1 when prescribed
  void set_zero();
  // Adds the block K (local dofs `local` of element e, rows and columns) to the matrix.
  template <typename Block>
  void add(int element, const Block& K, const int* local = nullptr, int n_local = -1);

  // Factorizes the current matrix and solves A x = b. Returns false when singular.
  bool solve(const Eigen::VectorXd& b, Eigen::VectorXd& x);
  // Solves A X = B for every column of B, to a relative residual |B - A X| / |B| <=
  // tolerance per column, with the factorization F of the last solve(), possibly of an
  // earlier matrix (Newton's previous iterate), refined against the current matrix:
  // X <- X + F^-1 (B - A X) (iterative refinement, Golub & Van Loan, Matrix
  // Computations, 4th ed., sec. 3.5.3), which converges at the rate |I - F^-1 A|, tiny
  // near a converged Newton state. Factorizes the current matrix when there is no
  // factorization yet or refinement stalls. Returns false when singular.
  bool solve_refined(const Eigen::MatrixXd& B, Eigen::MatrixXd& X, double tolerance);
  // Solves with the factorization of the last solve() (of an earlier matrix, possibly), without factorizing.
  // Returns false when there is none or the result is not finite.
  bool solve_factored(const Eigen::VectorXd& b, Eigen::VectorXd& x) const;
  bool factorized() const { return factor_ != Factor::None; }
  const std::string& solver_name() const { return solver_name_; }
  bool symmetric() const;
  // Whether every entry of the matrix is finite (an overflowed element must not reach a factorization).
  bool finite() const;
  // True once, right after the solve in which a symmetric tangent turned out not to be positive definite: from
  // then on this system skips the Cholesky attempt and solves with LU (an instability, a compressed structure
  // whose geometric stiffness went negative), without a library message at every iteration.
  bool became_indefinite();

private:
  std::vector<int> equation_;
  std::vector<std::vector<int>> element_dofs_;
  std::vector<std::vector<int>> positions_;  // per element: m x m entries into valuePtr, -1 when prescribed
  std::vector<int> transpose_position_;      // entry (r, c) -> entry (c, r)
  Eigen::SparseMatrix<double> matrix_;
  std::unique_ptr<Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower>> cholesky_;
  std::unique_ptr<Eigen::UmfPackLU<Eigen::SparseMatrix<double>>> lu_;
  std::unique_ptr<Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower>> ldlt_;
  enum class Choice { Undecided, Ldlt, Lu };
  enum class Factor { None, Cholesky, Ldlt, Lu };  // the factorization the last solve used
  bool saddle_point_ = false;
  bool indefinite_ = false, reported_indefinite_ = false;
  Choice choice_ = Choice::Undecided;
  Factor factor_ = Factor::None;
  std::string solver_name_ = "none";

  bool solve_ldlt(const Eigen::VectorXd& b, Eigen::VectorXd& x);
  bool solve_lu(const Eigen::VectorXd& b, Eigen::VectorXd& x);
  bool accurate(const Eigen::VectorXd& b, const Eigen::VectorXd& x) const;
  Eigen::MatrixXd solve_factored(const Eigen::MatrixXd& B) const;
};

template <typename Block>
void SparseSystem::add(int element, const Block& K, const int* local, int n_local) {
  const std::vector<int>& pos = positions_[element];
  const int m = static_cast<int>(element_dofs_[element].size());
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
