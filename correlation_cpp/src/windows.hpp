// The hot loops of calfit's DIC windows (orchestrator/measure/dic.py): the ZNCC integer search, the
// inverse-compositional Gauss-Newton (IC-GN) iterations with an affine or a quadratic window
// (orchestrator/measure/shape.py) and, given the error model's maps, each window's terms of that model
// (error_model.hpp). Python keeps the images' preparation (the prefilter, the spline coefficients, the noise maps)
// and the error model's logic; these loops take what it computed and return, per window, where the search started
// Gauss-Newton, the warp it converged to and the window's error terms, as its own loops would have computed them.
// dic.py's module text says what each step is and why.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "error_model.hpp"
#include "image.hpp"

namespace calfit::correlation {

// What every window of one correlation reads (dic._Pair's part that the loops need).
struct Pair {
  Image reference;                      // the prefiltered reference
  Image spline;                         // cubic B-spline coefficients of the prefiltered deformed image (scipy's)
  Image grad_rows, grad_cols;           // the reference's spline gradients
  std::array<double, 6> to_deformed{};  // the first two rows of the 3x3 prior rigid motion on (column, row, 1)
  const double* prior = nullptr;        // (2, rows, cols) prior field (d_col, d_row) px, or none
  const ErrorMaps* errors = nullptr;    // the error model's maps (error_model.hpp), or none: warps only
};

struct Settings {
  int window_px = 16;
  int search_px = 64;
  int iterations = 20;                // dic.GAUSS_NEWTON_ITERATIONS
  double tolerance_px = 1e-4;         // dic.GAUSS_NEWTON_TOLERANCE_PX, on the translation step
  double tolerance_gradient = 1e-5;   // on the step of the displacement gradient (and of its derivatives)
  int shape_order = 1;                // the window's shape function: 1 affine, 2 quadratic (shape.WindowShape)
};

enum class Status : std::int8_t {
  matched = 0,            // searched and refined: start, peak_score and warp hold
  outside = 1,            // the window does not fit in the image
  flat = 2,               // the template's standard deviation is below 1e-12
  refinement_failed = 3,  // searched (start, peak_score hold) but IC-GN could not proceed: a flat or singular system
  not_finite = 4,         // a NaN or an infinity in the window, its search area or the prior: rejected, not guessed
};

struct WindowResult {
  Status status = Status::outside;
  std::array<double, 2> start{};   // (d_col, d_row) px, the integer peak refined by a parabola
  double peak_score = 0.0;         // the ZNCC at the integer peak
  // the final map's rows x' and y' over the monomials (shape.py): (dx, dy, 1) affine, the first 6 values;
  // (dx^2, dx dy, dy^2, dx, dy, 1) quadratic, all 12
  std::array<double, 12> warp{};
  int iterations = 0;
  WindowError error;   // filled when the pair carries the error model's maps (status matched or refinement_failed)
};

// The ZNCC of `tmpl` (w x w) at every integer shift inside `patch` (p x p), (p - w + 1)^2 row-major values, as
// skimage.feature.match_template(patch, tmpl) gives them (0 where the patch is flat).
std::vector<double> zncc_map(const std::vector<double>& patch, std::ptrdiff_t p, const std::vector<double>& tmpl,
                             std::ptrdiff_t w);

// One window centred at the integer pixel (row, col); used: its w * w pixels that IC-GN matches (row-major).
WindowResult match_window(const Pair& pair, const Settings& settings, std::ptrdiff_t row, std::ptrdiff_t col,
                          const bool* used);

// Every window of (count, 2) centres and (count, w * w) pixel sets, shared among `threads` threads.
std::vector<WindowResult> match_windows(const Pair& pair, const Settings& settings, const std::int64_t* centres,
                                        std::size_t count, const bool* used, int threads);

}  // namespace calfit::correlation
