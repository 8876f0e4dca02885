// Each window's terms of the DIC error model (orchestrator/measure/prefilter.py and dic._inverse_compositional):
// the ZNCC at the match, of the prefiltered and of the raw images; the covariance of the window centre's
// displacement under the images' noise and per unit variance of the edges' position, each spread through the
// prefilter; and the sums its residual adds to the pooled estimate of the edges' error (prefilter.EdgeResiduals).
// Python's own loops compute the same from the same inputs (dic.correlate(..., compiled=False)), the reference
// these are held to.
#pragma once

#include <array>
#include <limits>
#include <vector>

#include "image.hpp"
#include "window_system.hpp"

namespace calfit::correlation {

// dic._inverse_compositional rejects a window whose Gauss-Newton matrix is worse conditioned than this
constexpr double kMaxCondition = 1e10;

// The maps every window's error terms read (dic._Pair's error-model part), on the reference's grid.
struct ErrorMaps {
  Image raw_reference, raw_spline;   // the images as given, when the pair's were prefiltered (empty: they are raw)
  Image noise_q, edge_q;             // G^2 * rho and G^2 * |grad I0|^2 (prefilter.Prefilter.squared_kernel_response)
  Image rho_raw, edge_raw;           // rho and |grad I0|^2, padded by the kernel's radius on every side
  std::vector<double> kernel{1.0};   // the prefilter's 1-D taps, 2 radius + 1 of them ({1}: no prefilter)
  double noise_gain = 1.0;           // sum G^2 (Prefilter.noise_gain)
  double derivative_noise_gain = 1.0;   // Prefilter.derivative_noise_gain
  std::array<double, 2> noise_sigma{};  // the raw noise of the reference and the deformed image
  // dic._finished's rules, by which a window is measured at its search's start instead: Gauss-Newton left the start
  // by more than max_refinement_px, or ended below the integer peak's ZNCC by more than zncc_slack
  double max_refinement_px = 3.0, zncc_slack = 0.02;
  std::ptrdiff_t radius() const { return (static_cast<std::ptrdiff_t>(kernel.size()) - 1) / 2; }
};

struct WindowError {
  bool conditioned = false;   // the Gauss-Newton matrix's condition number is at most kMaxCondition
  bool textured = false;      // its denoised part is positive definite: the texture rises above the noise
  double zncc = 0.0;          // of the prefiltered images at the match
  double confidence = 0.0;    // of the raw images at the match (the ZNCC the user reads)
  bool at_start = true;       // measured at the search's start (not conditioned, no warp, or by dic._finished's rules)
  double start_confidence = 0.0;   // of the raw images at the integer search's start, when at_start
  double variance = std::numeric_limits<double>::infinity();   // s_e^2, the raw noise in the normalised difference
  std::array<double, 4> covariance{};        // (col, row)^2 px^2 under the images' noise
  std::array<double, 4> edge_covariance{};   // the same per unit s_edge^2
  std::array<double, 5> edge_sums{};         // prefilter.EdgeResiduals: count, z, zz, y, yz
};

// The error terms of a window whose IC-GN system is `system`, matched by `warp` (null: refinement failed, only the
// start's confidence is read) from the integer search's `start` and its `peak_score`; `spline` and `reference` the
// pair's (prefiltered) deformed spline and reference, `to_deformed` the prior rigid motion.
WindowError window_error(const WindowSystem& system, const ErrorMaps& maps, const Image& reference,
                         const Image& spline, const std::array<double, 6>& to_deformed, const Warp* warp,
                         const std::array<double, 2>& start, double peak_score);

}  // namespace calfit::correlation
