// StaticAnalysis: the line search along a Newton correction (see line_search() in static_analysis.hpp).
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <cmath>

namespace calfit {

namespace {

// A step is accepted once the slope along it has fallen to this fraction of the starting slope: Crisfield's
// "slack" line search (Non-linear Finite Element Analysis of Solids and Structures, vol. 1, sec. 9.3.2, who
// advises 0.5 to 0.8); a tighter search costs residual evaluations that Newton's next iteration spends better.
constexpr double kSlopeTolerance = 0.5;
constexpr int kMaxSearchEvaluations = 6;
constexpr double kSmallestStep = 1.0 / 64.0;

}  // namespace

double StaticAnalysis::slope_along(const Eigen::VectorXd& direction) const {
  double slope = 0.0;
  for (int d = 0; d < n_dofs_; ++d)
    if (system_->equation(d) >= 0) slope += direction[d] * residual_[d];
  return slope;
}

StaticAnalysis::Evaluation StaticAnalysis::line_search(Eigen::VectorXd& u, const Eigen::VectorXd& du, double lambda,
                                                       const Evaluation& start) {
  // residual_ holds R(u): the slope of the potential along du at eta = 0.
  const double slope0 = slope_along(du);
  Eigen::VectorXd trial = u + du;
  Evaluation full = evaluate(trial, lambda, true);
  if (full.ok && full.norm <= start.norm) {
    u = trial;
    return full;
  }

  if (slope0 < 0.0) {
    // The full step overshoots (or inverts an element). With a symmetric positive tangent du descends the
    // potential energy, and the step length is the root of its slope s(eta) = du . R(u + eta du) (Crisfield,
    // sec. 9.3.2; Matthies & Strang 1979): the Illinois variant of regula falsi between the last eta with
    // s < 0 and the first with s > 0 (or that inverts an element, where the energy is infinite). A garment
    // band let go from its inflated circle is where this matters: its linearized breathing mode overshoots (the
    // ring's pressure-stretch curve flattens near the inflated state), and once it closes onto the skin the full
    // step drives new contact nodes deep into the leg. Halving until |R| fell took steps of 1/16 for ten
    // iterations in a row there; on the 5k-DOF leg of benchmarks/engine.py this search took the garment's
    // put-on from 293 Newton iterations to 128 at the same penalty. With hybrid elements the potential is a
    // Lagrangian, stationary rather than minimal in the pressures, and s(eta) = 0 is still its stationary point
    // along du: the same leg on CPE6H went from 234 iterations to 32.
    double low = 0.0, s_low = slope0, high = 1.0, s_high = full.ok ? slope_along(du) : HUGE_VAL;
    int kept_side = 0;  // which end the last two updates kept (Illinois: halve the stale end's slope)
    double best_eta = 0.0, best_slope = std::abs(slope0);
    for (int k = 0; k < kMaxSearchEvaluations; ++k) {
      double eta = std::isfinite(s_high) ? low + (high - low) * s_low / (s_low - s_high) : 0.5 * (low + high);
      eta = std::clamp(eta, low + 0.1 * (high - low), high - 0.1 * (high - low));
      trial = u + eta * du;
      const Evaluation probe = evaluate(trial, lambda, false);
      const double s = probe.ok ? slope_along(du) : HUGE_VAL;
      if (probe.ok && std::abs(s) < best_slope) {
        best_eta = eta;
        best_slope = std::abs(s);
      }
      if (probe.ok && std::abs(s) <= kSlopeTolerance * std::abs(slope0)) break;
      if (s < 0.0) {
        if (kept_side == -1 && std::isfinite(s_high)) s_high *= 0.5;
        low = eta;
        s_low = s;
        kept_side = -1;
      } else {
        if (kept_side == 1) s_low *= 0.5;
        high = eta;
        s_high = s;
        kept_side = 1;
      }
    }
    if (best_eta >= kSmallestStep) {
      u += best_eta * du;
      return evaluate(u, lambda, true);
    }
  }

  // A direction along which the potential does not fall at first (s(0) >= 0: an indefinite tangent), or a search
  // that found no shorter slope: backtracking on |R|, halving the step while it fails to reduce the residual (or
  // inverts an element).
  for (double eta = 0.5; eta > 0.01; eta *= 0.5) {
    trial = u + eta * du;
    const Evaluation shorter = evaluate(trial, lambda, false);
    if (shorter.ok && shorter.norm < start.norm) {
      u = trial;
      return evaluate(u, lambda, true);
    }
  }
  if (!full.ok) return full;  // every step turns an element inside out
  u += du;                    // accept the full step; Newton may rise before it falls
  return evaluate(u, lambda, true);
}

}  // namespace calfit
