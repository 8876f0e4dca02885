// Images as the DIC windows read them: a row-major grid the caller owns, and its cubic B-spline as scipy evaluates
// it (orchestrator/measure/dic.py samples the deformed image and differentiates the reference through it).
#pragma once

#include <cstddef>

namespace calfit::correlation {

// A row-major image (or spline coefficients) the caller owns.
struct Image {
  const double* data = nullptr;
  std::ptrdiff_t rows = 0, cols = 0;
  double at(std::ptrdiff_t r, std::ptrdiff_t c) const { return data[r * cols + c]; }
  bool empty() const { return data == nullptr; }
};

// The value at (row, col) of the cubic B-spline of `coefficients`, as scipy.ndimage.map_coordinates(order=3,
// prefilter=False, mode="nearest") evaluates it: the coefficients beyond the edge are those at the edge.
double sample_spline(const Image& coefficients, double row, double col);

// (d/drow, d/dcolumn) at every pixel of the cubic B-spline of `coefficients`, by a central difference of `step`
// pixels of the spline itself (dic.spline_derivatives), into two rows x cols grids. The same sums as sample_spline
// at each of the four points, in the same order, so the same values to the last bit; but at a pixel one axis of
// each point is an integer, whose weights are the same along a whole line, so each line is combined once along
// that axis first (six products a pixel instead of 64).
void spline_gradient(const Image& coefficients, double step, double* along_rows, double* along_cols);

}  // namespace calfit::correlation
