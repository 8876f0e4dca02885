// Global sparse system: see sparse_system.hpp.
#include "solver/sparse_system.hpp"

#include <algorithm>
#include <cmath>

namespace calfit {

SparseSystem::SparseSystem(const std::vector<std::vector<int>>& element_dofs, const std::vector<char>& free)
    : equation_(free.size(), -1), element_dofs_(element_dofs) {
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

bool SparseSystem::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (size() == 0) {
    x.resize(0);
    return true;
  }
  if (symmetric()) {
    if (!cholesky_) {
      cholesky_ = std::make_unique<Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower>>();
      cholesky_->analyzePattern(matrix_);
    }
    cholesky_->factorize(matrix_);
    if (cholesky_->info() == Eigen::Success) {
      x = cholesky_->solve(b);
      solver_name_ = "cholmod";
      if (cholesky_->info() == Eigen::Success && x.allFinite()) return true;
    }
  }
  if (!lu_) {
    lu_ = std::make_unique<Eigen::UmfPackLU<Eigen::SparseMatrix<double>>>();
    lu_->analyzePattern(matrix_);
  }
  lu_->factorize(matrix_);
  if (lu_->info() != Eigen::Success) return false;
  x = lu_->solve(b);
  solver_name_ = "umfpack";
  return lu_->info() == Eigen::Success && x.allFinite();
}

}  // namespace calfit
