// Global sparse system: see sparse_system.hpp.
#include "solver/sparse_system.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

namespace calfit {

SparseSystem::SparseSystem(const std::vector<std::vector<int>>& element_dofs, const std::vector<char>& free,
                           bool saddle_point)
    : equation_(free.size(), -1), element_dofs_(element_dofs), saddle_point_(saddle_point) {
  int n = 0;
  for (std::size_t d = 0; d < free.size(); ++d)
    if (free[d]) equation_[d] = n++;

  std::vector<std::vector<int>> rows(n);
  for (const std::vector<int>& dofs : element_dofs)
    for (int dc : dofs) {
      const int c = equation_[dc];
      if (c < 0) continue;
      for (int dr : dofs)
        if (equation_[dr] >= 0) rows[c].push_back(equation_[dr]);
    }
  std::size_t nnz = 0;
  for (std::vector<int>& r : rows) {
    std::sort(r.begin(), r.end());
    r.erase(std::unique(r.begin(), r.end()), r.end());
    nnz += r.size();
  }
  matrix_.resize(n, n);
  matrix_.reserve(static_cast<Eigen::Index>(nnz));
  for (int c = 0; c < n; ++c) {
    matrix_.startVec(c);
    for (int r : rows[c]) matrix_.insertBack(r, c) = 0.0;
  }
  matrix_.finalize();

  const int* outer = matrix_.outerIndexPtr();
  const int* inner = matrix_.innerIndexPtr();
  auto entry = [&](int r, int c) {
    const int* first = inner + outer[c];
    const int* last = inner + outer[c + 1];
    return static_cast<int>(std::lower_bound(first, last, r) - inner);
  };
  positions_.resize(element_dofs.size());
  for (std::size_t e = 0; e < element_dofs.size(); ++e) {
    const std::vector<int>& dofs = element_dofs[e];
    const int m = static_cast<int>(dofs.size());
    std::vector<int>& pos = positions_[e];
    pos.assign(static_cast<std::size_t>(m * m), -1);
    for (int j = 0; j < m; ++j)
      for (int i = 0; i < m; ++i) {
        const int r = equation_[dofs[i]], c = equation_[dofs[j]];
        if (r >= 0 && c >= 0) pos[i + m * j] = entry(r, c);
      }
  }
  transpose_position_.resize(nnz);
  for (int c = 0; c < n; ++c)
    for (int p = outer[c]; p < outer[c + 1]; ++p) transpose_position_[p] = entry(c, inner[p]);
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

bool SparseSystem::solve_ldlt(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (!ldlt_) {
    ldlt_ = std::make_unique<Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower>>();
    ldlt_->setMode(Eigen::CholmodLDLt);
    ldlt_->cholmod().print = 0;  // a failure is handled here, by UMFPACK
    ldlt_->analyzePattern(matrix_);
  }
  ldlt_->factorize(matrix_);
  if (ldlt_->info() != Eigen::Success) return false;
  x = ldlt_->solve(b);
  solver_name_ = "cholmod-ldlt";
  factor_ = Factor::Ldlt;
  return ldlt_->info() == Eigen::Success && accurate(b, x);
}

bool SparseSystem::solve_lu(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (!lu_) {
    lu_ = std::make_unique<Eigen::UmfPackLU<Eigen::SparseMatrix<double>>>();
    lu_->analyzePattern(matrix_);
  }
  lu_->factorize(matrix_);
  if (lu_->info() != Eigen::Success) return false;
  x = lu_->solve(b);
  solver_name_ = "umfpack";
  factor_ = Factor::Lu;
  return lu_->info() == Eigen::Success && x.allFinite();
}

bool SparseSystem::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (size() == 0) {
    x.resize(0);
    return true;
  }
  const bool is_symmetric = symmetric();
  if (!saddle_point_ && is_symmetric && !indefinite_) {
    if (!cholesky_) {
      cholesky_ = std::make_unique<Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower>>();
      cholesky_->cholmod().print = 0;  // a lost definiteness is handled below, by UMFPACK, not printed
      cholesky_->analyzePattern(matrix_);
    }
    cholesky_->factorize(matrix_);
    if (cholesky_->info() == Eigen::Success) {
      x = cholesky_->solve(b);
      solver_name_ = "cholmod";
      factor_ = Factor::Cholesky;
      if (cholesky_->info() == Eigen::Success && x.allFinite()) return true;
    }
    indefinite_ = true;
  }
  if (saddle_point_ && is_symmetric && choice_ != Choice::Lu) {
    if (choice_ == Choice::Ldlt) {
      if (solve_ldlt(b, x)) return true;
      choice_ = Choice::Lu;  // a zero pivot: D1 = 0 or an instability
    } else {
      using clock = std::chrono::steady_clock;
      const auto t0 = clock::now();
      Eigen::VectorXd x_ldlt;
      const bool ldlt_ok = solve_ldlt(b, x_ldlt);
      const auto t1 = clock::now();
      const bool lu_ok = solve_lu(b, x);
      const auto t2 = clock::now();
      choice_ = ldlt_ok && (!lu_ok || t1 - t0 < t2 - t1) ? Choice::Ldlt : Choice::Lu;
      if (choice_ == Choice::Ldlt) {
        x = x_ldlt;
        solver_name_ = "cholmod-ldlt";
        factor_ = Factor::Ldlt;
        return true;
      }
      solver_name_ = "umfpack";
      return lu_ok;
    }
  }
  return solve_lu(b, x);
}

Eigen::MatrixXd SparseSystem::solve_factored(const Eigen::MatrixXd& B) const {
  switch (factor_) {
    case Factor::Cholesky: return cholesky_->solve(B);
    case Factor::Ldlt: return ldlt_->solve(B);
    case Factor::Lu: return lu_->solve(B);
    case Factor::None: break;
  }
  return Eigen::MatrixXd::Constant(B.rows(), B.cols(), std::numeric_limits<double>::quiet_NaN());
}

bool SparseSystem::solve_factored(const Eigen::VectorXd& b, Eigen::VectorXd& x) const {
  if (factor_ == Factor::None) return false;
  x = solve_factored(Eigen::MatrixXd(b)).col(0);
  return x.allFinite();
}

bool SparseSystem::solve_refined(const Eigen::MatrixXd& B, Eigen::MatrixXd& X, double tolerance) {
  if (size() == 0 || B.cols() == 0) {
    X.setZero(size(), B.cols());
    return true;
  }
  const Eigen::RowVectorXd norms = B.colwise().norm().cwiseMax(1e-300);
  auto relative_residual = [&] { return ((B - matrix_ * X).colwise().norm().array() / norms.array()).maxCoeff(); };
  for (int attempt = 0; attempt < 2; ++attempt) {
    if (factor_ == Factor::None || attempt == 1) {
      Eigen::VectorXd first;
      if (!solve(B.col(0), first)) return false;  // factorizes the current matrix
    }
    X = solve_factored(B);
    double previous = std::numeric_limits<double>::infinity();
    for (int it = 0; it < 10 && X.allFinite(); ++it) {
      const double r = relative_residual();
      if (r <= tolerance) return true;
      if (!(r < 0.5 * previous)) break;  // stalled: factorize the current matrix
      previous = r;
      X += solve_factored(B - matrix_ * X);
    }
  }
  return false;
}

}  // namespace calfit
