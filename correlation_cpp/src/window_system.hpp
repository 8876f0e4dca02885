// One window's IC-GN system linearised at the reference (dic._inverse_compositional): its pixels, its normalised
// template, the steepest-descent images and their Gauss-Newton matrix. windows.cpp builds it once per window and
// iterates on it; error_model.cpp reads the window's error terms from it.
#pragma once

#include <array>
#include <cmath>
#include <cstddef>
#include <vector>

#include "image.hpp"

namespace calfit::correlation {

struct WindowSystem {
  std::ptrdiff_t r0 = 0, c0 = 0, size = 0;   // the square's corner and side
  int terms = 3;                             // basis functions per displacement component: 3 affine, 6 quadratic
  std::vector<std::ptrdiff_t> pixels;        // the used pixels, r * size + c within the square, row-major
  std::vector<double> f;                     // the template at them, mean-free and of unit norm (f^)
  double f_norm = 0.0;
  // (n, 2 terms) the steepest-descent images with the mean and f^ projected out, and their (2 terms)^2 Gauss-Newton
  // matrix, neither divided by f_norm (dic.zero_normalised_steepest_descent)
  std::vector<double> steepest, hessian;
  std::vector<double> monomials;             // (n, terms) each pixel's monomials (shape.py)
  std::vector<double> prior_col, prior_row;  // the prior field at each pixel (px)
  int parameters() const { return 2 * terms; }
  double centre_row() const { return static_cast<double>(r0) + (static_cast<double>(size) - 1.0) / 2.0; }
  double centre_col() const { return static_cast<double>(c0) + (static_cast<double>(size) - 1.0) / 2.0; }
};

// A map's rows x', y' over the monomials (windows.hpp, WindowResult::warp).
using Warp = std::array<double, 12>;

// The map of a pure translation by (d_col, d_row) px (shape.WindowShape.translated).
inline Warp translation_warp(int terms, const std::array<double, 2>& displacement) {
  Warp warp{};
  warp[terms - 3] = 1.0;
  warp[2 * terms - 2] = 1.0;
  warp[terms - 1] = displacement[0];
  warp[2 * terms - 1] = displacement[1];
  return warp;
}

// The deformed image's spline at the window's pixels moved by the map `warp`, the prior field and the prior rigid
// motion `to_deformed` (dic._sample), into `out` (n values).
inline void sample_through(const Image& spline, const std::array<double, 6>& to_deformed, const WindowSystem& system,
                           const Warp& warp, std::vector<double>& out) {
  const int k = system.terms;
  const double centre_col = system.centre_col(), centre_row = system.centre_row();
  out.resize(system.pixels.size());
  for (std::size_t i = 0; i < system.pixels.size(); ++i) {
    const double* m = &system.monomials[i * k];
    double moved_col = 0.0, moved_row = 0.0;
    for (int j = 0; j < k; ++j) {
      moved_col += warp[j] * m[j];
      moved_row += warp[k + j] * m[j];
    }
    const double col = centre_col + moved_col + system.prior_col[i], row = centre_row + moved_row + system.prior_row[i];
    out[i] = sample_spline(spline, to_deformed[3] * col + to_deformed[4] * row + to_deformed[5],
                           to_deformed[0] * col + to_deformed[1] * row + to_deformed[2]);
  }
}

// (values - mean) / norm in place; returns the norm (dic._normalise; a zero norm leaves the values mean-free).
inline double normalise(std::vector<double>& values) {
  double mean = 0.0;
  for (double v : values) mean += v;
  mean /= static_cast<double>(values.size());
  double squares = 0.0;
  for (double& v : values) {
    v -= mean;
    squares += v * v;
  }
  const double norm = std::sqrt(squares);
  if (norm > 0.0)
    for (double& v : values) v /= norm;
  return norm;
}

}  // namespace calfit::correlation
