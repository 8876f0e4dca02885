#include "error_model.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace calfit::correlation {
namespace {

using Matrix = Eigen::MatrixXd;
using RowMajorMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// G * maps for `count` maps that are zero outside the window's square, each on the square grown by the kernel's
// radius on every side, row-major (Prefilter.spread: the kernel is symmetric, so spreading is filtering). values:
// (count, n) at the window's used pixels.
RowMajorMatrix spread(const std::vector<double>& kernel, const WindowSystem& system, const double* values, int count) {
  const auto reach = (static_cast<std::ptrdiff_t>(kernel.size()) - 1) / 2;
  const std::ptrdiff_t side = system.size + 2 * reach, cells = side * side;
  const std::size_t n = system.pixels.size();
  RowMajorMatrix out = RowMajorMatrix::Zero(count, cells);
  std::vector<double> padded(cells), along_rows(cells);
  for (int j = 0; j < count; ++j) {
    std::fill(padded.begin(), padded.end(), 0.0);
    for (std::size_t i = 0; i < n; ++i) {
      const std::ptrdiff_t r = system.pixels[i] / system.size, c = system.pixels[i] % system.size;
      padded[(r + reach) * side + c + reach] = values[i * count + j];
    }
    // scipy's correlate1d with zeros beyond the grid, along the rows and then along the columns
    for (std::ptrdiff_t r = 0; r < side; ++r)
      for (std::ptrdiff_t c = 0; c < side; ++c) {
        double sum = 0.0;
        for (std::ptrdiff_t t = -reach; t <= reach; ++t)
          if (r + t >= 0 && r + t < side) sum += kernel[t + reach] * padded[(r + t) * side + c];
        along_rows[r * side + c] = sum;
      }
    for (std::ptrdiff_t r = 0; r < side; ++r)
      for (std::ptrdiff_t c = 0; c < side; ++c) {
        double sum = 0.0;
        for (std::ptrdiff_t t = -reach; t <= reach; ++t)
          if (c + t >= 0 && c + t < side) sum += kernel[t + reach] * along_rows[r * side + c + t];
        out(j, r * side + c) = sum;
      }
  }
  return out;
}

// A padded raw map (ErrorMaps::rho_raw, edge_raw) on the window's square grown by the kernel's radius (dic._Pair.around)
Eigen::VectorXd around(const Image& padded, const WindowSystem& system, std::ptrdiff_t reach) {
  const std::ptrdiff_t side = system.size + 2 * reach;
  Eigen::VectorXd out(side * side);
  for (std::ptrdiff_t r = 0; r < side; ++r)
    for (std::ptrdiff_t c = 0; c < side; ++c) out(r * side + c) = padded.at(system.r0 + r, system.c0 + c);
  return out;
}

// tr(P C) / tr(C): the share of an error of the raw pixels that the window's own fit takes into its parameters
// (dic._absorbed_share)
double absorbed_share(const Eigen::PartialPivLU<Matrix>& hessian, const Matrix& gram, const RowMajorMatrix& normalisation,
                      const Eigen::VectorXd& variance_raw, double total) {
  if (total <= 0.0) return 0.0;
  const double taken =
      hessian.solve(gram).trace() + (normalisation.array().square().rowwise() * variance_raw.transpose().array()).sum();
  return std::clamp(taken / total, 0.0, 1.0);
}

// The ZNCC of the raw windows (dic._raw_zncc): the raw reference's template and the raw deformed spline through
// the map, over the window's used pixels
double raw_zncc(const WindowSystem& system, const Image& reference, const Image& spline,
                const std::array<double, 6>& to_deformed, const Warp& warp) {
  std::vector<double> f(system.pixels.size()), g;
  for (std::size_t i = 0; i < f.size(); ++i)
    f[i] = reference.at(system.r0 + system.pixels[i] / system.size, system.c0 + system.pixels[i] % system.size);
  sample_through(spline, to_deformed, system, warp, g);
  const double f_norm = normalise(f), g_norm = normalise(g);
  if (!(f_norm > 0.0) || !(g_norm > 0.0)) return 0.0;
  double dot = 0.0;
  for (std::size_t i = 0; i < f.size(); ++i) dot += f[i] * g[i];
  return dot;
}

}  // namespace

WindowError window_error(const WindowSystem& system, const ErrorMaps& maps, const Image& reference,
                         const Image& spline, const std::array<double, 6>& to_deformed, const Warp* warp,
                         const std::array<double, 2>& start, double peak_score) {
  WindowError out;
  const bool raw_given = !maps.raw_spline.empty();
  const Image& raw_reference = raw_given ? maps.raw_reference : reference;
  const Image& raw_spline = raw_given ? maps.raw_spline : spline;
  auto at_start = [&]() {
    out.at_start = true;
    out.start_confidence =
        raw_zncc(system, raw_reference, raw_spline, to_deformed, translation_warp(system.terms, start));
    return out;
  };
  const int k = system.terms, np = system.parameters();
  const Matrix hessian = Eigen::Map<const RowMajorMatrix>(system.hessian.data(), np, np);
  const Eigen::VectorXd eigenvalues = Eigen::SelfAdjointEigenSolver<Matrix>(hessian, Eigen::EigenvaluesOnly)
                                          .eigenvalues().cwiseAbs();
  out.conditioned = eigenvalues.minCoeff() > 0.0 && eigenvalues.maxCoeff() / eigenvalues.minCoeff() <= kMaxCondition;
  if (warp == nullptr || !out.conditioned) return at_start();

  const std::size_t n = system.pixels.size();
  std::vector<double> g;
  sample_through(spline, to_deformed, system, *warp, g);
  const double g_norm = normalise(g);
  double zncc = 0.0;
  for (std::size_t i = 0; i < n; ++i) zncc += system.f[i] * g[i];
  out.zncc = zncc;
  const double moved = std::max(std::abs((*warp)[k - 1] - start[0]), std::abs((*warp)[2 * k - 1] - start[1]));
  if (moved > maps.max_refinement_px || zncc < peak_score - maps.zncc_slack) return at_start();
  out.at_start = false;
  const double ratio = system.f_norm / g_norm * maps.noise_sigma[1];
  out.variance = maps.noise_sigma[0] * maps.noise_sigma[0] + ratio * ratio;
  out.confidence = raw_given ? raw_zncc(system, raw_reference, raw_spline, to_deformed, *warp) : zncc;

  // H_s = H - s_f^2 g^2 M_rho (dic.denoised_hessian): the moments of the basis over the whole square, weighted by
  // each used pixel's noise share
  const double half = (static_cast<double>(system.size) - 1.0) / 2.0;
  Matrix moments = Matrix::Zero(k, k);
  std::vector<bool> in_use(system.size * system.size, false);
  for (std::ptrdiff_t p : system.pixels) in_use[p] = true;
  double basis[6];
  for (std::ptrdiff_t r = 0; r < system.size; ++r)
    for (std::ptrdiff_t c = 0; c < system.size; ++c) {
      if (!in_use[r * system.size + c]) continue;
      const double weight = maps.noise_q.at(system.r0 + r, system.c0 + c) / maps.noise_gain;
      const double dx = static_cast<double>(c) - half, dy = static_cast<double>(r) - half;
      basis[0] = 1.0;
      basis[1] = dx;
      basis[2] = dy;
      if (k == 6) {
        basis[3] = 0.5 * dx * dx;
        basis[4] = dx * dy;
        basis[5] = 0.5 * dy * dy;
      }
      for (int a = 0; a < k; ++a)
        for (int b = 0; b < k; ++b) moments(a, b) += weight * basis[a] * basis[b];
    }
  Matrix signal = hessian;
  const double noise = maps.noise_sigma[0] * maps.noise_sigma[0] * maps.derivative_noise_gain;
  signal.topLeftCorner(k, k) -= noise * moments;
  signal.bottomRightCorner(k, k) -= noise * moments;
  Eigen::LLT<Matrix> cholesky(signal);
  out.textured = cholesky.info() == Eigen::Success;
  if (!out.textured) return out;

  // Cov p = s_e^2 H_s^-1 (G * S)^T rho (G * S) H_s^-1, and the edges' part per unit s_edge^2 (prefilter)
  const std::ptrdiff_t reach = maps.radius();
  const RowMajorMatrix spread_steepest = spread(maps.kernel, system, system.steepest.data(), np);
  const Eigen::VectorXd edge_raw = around(maps.edge_raw, system, reach), rho_raw = around(maps.rho_raw, system, reach);
  const Matrix edge_gram = spread_steepest * edge_raw.asDiagonal() * spread_steepest.transpose();
  const Matrix noise_gram = spread_steepest * rho_raw.asDiagonal() * spread_steepest.transpose();
  std::vector<double> directions(2 * n);   // the mean 1 / sqrt(n) and f^ (dic._normalisation_spread), (n, 2)
  for (std::size_t i = 0; i < n; ++i) {
    directions[2 * i] = 1.0 / std::sqrt(static_cast<double>(n));
    directions[2 * i + 1] = system.f[i];
  }
  const RowMajorMatrix normalisation = spread(maps.kernel, system, directions.data(), 2);
  std::vector<double> edge_q(n), noise_q(n);
  double edge_total = 0.0, noise_total = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    const std::ptrdiff_t r = system.r0 + system.pixels[i] / system.size, c = system.c0 + system.pixels[i] % system.size;
    edge_total += edge_q[i] = maps.edge_q.at(r, c);
    noise_total += noise_q[i] = maps.noise_q.at(r, c);
  }
  const Eigen::PartialPivLU<Matrix> lu(hessian);
  const double edge_kept = 1.0 - absorbed_share(lu, edge_gram, normalisation, edge_raw, edge_total);
  const double noise_kept = 1.0 - absorbed_share(lu, noise_gram, normalisation, rho_raw, noise_total);
  double count = 0.0, z = 0.0, zz = 0.0, y = 0.0, yz = 0.0;   // prefilter.EdgeResiduals.add
  for (std::size_t i = 0; i < n; ++i) {
    const double residual = (g[i] - system.f[i]) * system.f_norm;
    const double pixel_variance = out.variance * noise_kept * noise_q[i];
    const double yi = residual * residual / pixel_variance, zi = edge_kept * edge_q[i] / pixel_variance;
    count += 1.0;
    z += zi;
    zz += zi * zi;
    y += yi;
    yz += yi * zi;
  }
  out.edge_sums = {count, z, zz, y, yz};
  const Matrix inverse = signal.inverse();
  const int translation[2] = {0, k};
  const Matrix noise_sandwich = inverse * noise_gram * inverse, edge_sandwich = inverse * edge_gram * inverse;
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b) {
      out.covariance[2 * a + b] = out.variance * noise_sandwich(translation[a], translation[b]);
      out.edge_covariance[2 * a + b] = edge_sandwich(translation[a], translation[b]);
    }
  return out;
}

}  // namespace calfit::correlation
