#include "image.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

namespace calfit::correlation {
namespace {

// The four cubic B-spline weights of the knots floor(x) - 1 .. floor(x) + 2 at the fraction t = x - floor(x).
inline void cubic_weights(double t, double* w) {
  const double s = 1.0 - t;
  w[0] = s * s * s / 6.0;
  w[1] = (t * t * (t - 2.0) * 3.0 + 4.0) / 6.0;
  w[2] = (s * s * (s - 2.0) * 3.0 + 4.0) / 6.0;
  w[3] = t * t * t / 6.0;
}

// A coordinate far beyond the edge reads the edge's coefficients, as one just beyond it does: clamping it first keeps
// floor() and the index arithmetic finite for any finite input.
inline void axis_taps(double x, std::ptrdiff_t length, std::ptrdiff_t* index, double* weight) {
  x = std::clamp(x, -4.0, static_cast<double>(length) + 3.0);
  const double base = std::floor(x);
  cubic_weights(x - base, weight);
  const auto first = static_cast<std::ptrdiff_t>(base) - 1;
  for (std::ptrdiff_t k = 0; k < 4; ++k) index[k] = std::clamp(first + k, std::ptrdiff_t{0}, length - 1);
}

// One point's taps along an axis: the four knots and their weights.
struct Taps {
  std::ptrdiff_t index[4];
  double weight[4];
};

std::vector<Taps> taps_along(std::ptrdiff_t length, double offset) {
  std::vector<Taps> out(static_cast<std::size_t>(length));
  for (std::ptrdiff_t k = 0; k < length; ++k)
    axis_taps(static_cast<double>(k) + offset, length, out[k].index, out[k].weight);
  return out;
}

// sample_spline's inner sum: one line's coefficients at a point's four column taps
inline double along_line(const double* line, const Taps& c) {
  return c.weight[0] * line[c.index[0]] + c.weight[1] * line[c.index[1]] + c.weight[2] * line[c.index[2]] +
         c.weight[3] * line[c.index[3]];
}

// sample_spline's outer sum over a point's four row taps of the lines' inner sums (`lines`, rows x cols)
inline double across_lines(const std::vector<double>& lines, std::ptrdiff_t cols, const Taps& r, std::ptrdiff_t c) {
  double value = 0.0;
  for (int i = 0; i < 4; ++i) value += r.weight[i] * lines[r.index[i] * cols + c];
  return value;
}

}  // namespace

double sample_spline(const Image& coefficients, double row, double col) {
  double wr[4], wc[4];
  const double base_row = std::floor(row), base_col = std::floor(col);
  // a point whose 4 x 4 knots all lie inside the grid (most of them): no clamping, the same sums in the same order
  if (base_row >= 1.0 && base_row + 2.0 < static_cast<double>(coefficients.rows) && base_col >= 1.0 &&
      base_col + 2.0 < static_cast<double>(coefficients.cols)) {
    cubic_weights(row - base_row, wr);
    cubic_weights(col - base_col, wc);
    const double* line = coefficients.data + (static_cast<std::ptrdiff_t>(base_row) - 1) * coefficients.cols +
                         static_cast<std::ptrdiff_t>(base_col) - 1;
    double value = 0.0;
    for (int i = 0; i < 4; ++i, line += coefficients.cols)
      value += wr[i] * (wc[0] * line[0] + wc[1] * line[1] + wc[2] * line[2] + wc[3] * line[3]);
    return value;
  }
  std::ptrdiff_t rows[4], cols[4];
  axis_taps(row, coefficients.rows, rows, wr);
  axis_taps(col, coefficients.cols, cols, wc);
  double value = 0.0;
  for (int i = 0; i < 4; ++i) {
    const double* line = coefficients.data + rows[i] * coefficients.cols;
    value += wr[i] * (wc[0] * line[cols[0]] + wc[1] * line[cols[1]] + wc[2] * line[cols[2]] + wc[3] * line[cols[3]]);
  }
  return value;
}

void spline_gradient(const Image& coefficients, double step, double* along_rows, double* along_cols) {
  const std::ptrdiff_t rows = coefficients.rows, cols = coefficients.cols;
  const std::vector<Taps> row_on = taps_along(rows, 0.0), col_on = taps_along(cols, 0.0);
  const std::vector<Taps> row_up = taps_along(rows, step), row_down = taps_along(rows, -step);
  const std::vector<Taps> col_up = taps_along(cols, step), col_down = taps_along(cols, -step);
  // each line's inner sum at the pixels' own columns, and at the columns +- step
  std::vector<double> on(rows * cols), up(rows * cols), down(rows * cols);
  for (std::ptrdiff_t r = 0; r < rows; ++r) {
    const double* line = coefficients.data + r * cols;
    for (std::ptrdiff_t c = 0; c < cols; ++c) {
      on[r * cols + c] = along_line(line, col_on[c]);
      up[r * cols + c] = along_line(line, col_up[c]);
      down[r * cols + c] = along_line(line, col_down[c]);
    }
  }
  for (std::ptrdiff_t r = 0; r < rows; ++r)
    for (std::ptrdiff_t c = 0; c < cols; ++c) {
      along_rows[r * cols + c] =
          (across_lines(on, cols, row_up[r], c) - across_lines(on, cols, row_down[r], c)) / (2 * step);
      along_cols[r * cols + c] =
          (across_lines(up, cols, row_on[r], c) - across_lines(down, cols, row_on[r], c)) / (2 * step);
    }
}

}  // namespace calfit::correlation
