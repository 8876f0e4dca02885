// StaticAnalysis::run_step: the load increments of a step and the Newton iterations of each (increment control,
// linear solves, line search): see newton.hpp.
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

namespace calfit {

using namespace analysis_support;

namespace {

// The directional difference of the residual along a prescribed increment moves the prescribed dofs by this
// fraction of the model's size: far above round-off, far below any strain the elements could notice.
constexpr double kDirectionalStep = 1e-7;

// The next increment after one that converged in `iterations` Newton iterations (`previous`: the increment
// before it, 0 if none).
// - Driven by prescribed displacements: the iteration count measures how nonlinear the increment was, and the
//   next one is scaled by (N_d / N)^(1/2) when it took more than N_d = kEasyIterations (Crisfield, Non-linear
//   Finite Element Analysis of Solids and Structures, vol. 1, sec. 9.5.1), at least halved; easy twice in a row,
//   1.5 times longer (CalculiX's growth rule). A compressed block then keeps to 3-4 iterations per increment
//   instead of meeting a 9-iteration one near its barrelling.
// - Driven by loads alone, or with penalty contact, the count follows other things (a nearly incompressible
//   displacement element's volumetric overshoot, changes of contact status) and shrinking only crawls: there an
//   increment grows 1.5 times after one of at most kLoadEasyIterations and shrinks only when it fails.
constexpr int kEasyIterations = 3;
constexpr int kRateCheckIterations = 3;     // Newton iterations before the contraction is checked
constexpr double kSlowContraction = 0.1;    // a residual that falls by less than this per iteration is slow
constexpr int kLoadEasyIterations = 5;
// Slip releases (release_slipping_contacts) allowed in one increment. A release is a severe discontinuity: the
// residual jumps and Newton starts again from the state it had nearly converged to, so each round of iterations
// between releases gets the whole equilibrium budget (SolverSettings::max_iterations), and the releases have a
// limit of their own, as Abaqus/Standard counts severe-discontinuity iterations apart from equilibrium ones
// (*CONTROLS, PARAMETERS=TIME INCREMENTATION: I_S, default 12). A step whose increment is not ramped (a pin
// released at its start) cannot be cut back into smaller slip events: on the leg under an uneven band with
// mu = 0.02, releasing the band's pins took 26 iterations over several releases, where one budget of 25 failed
// at every increment size.
constexpr int kMaxSlipReleases = 12;

// How exactly a Newton correction is solved when GMRES solves it (an earlier factor, the symmetric part of an
// unsymmetric tangent): to |K du + R| <= eta |R| with eta = 0.1 r, r the current relative residual, between
// SparseSystem::kExactSolve and 1e-2. The next residual is then eta |R| + O(|R|^2), and eta = O(r) keeps Newton's
// convergence quadratic (an inexact Newton method: Dembo, Eisenstat & Steihaug, SIAM J. Numer. Anal. 19 (1982)
// 400-408) while the early corrections, far from the solution, take a few GMRES steps instead of 8-16.
double forcing_term(const std::vector<double>& residual_norms) {
  if (residual_norms.empty()) return SparseSystem::kExactSolve;  // a predictor: solved as exactly as it can be
  return std::clamp(0.1 * residual_norms.back(), SparseSystem::kExactSolve, 1e-2);
}

double next_increment_factor(int iterations, int previous, bool displacement_driven) {
  if (!displacement_driven) return iterations <= kLoadEasyIterations ? 1.5 : 1.0;
  if (iterations > kEasyIterations)
    return std::max(std::sqrt(static_cast<double>(kEasyIterations) / iterations), 0.5);
  return previous > 0 && previous <= kEasyIterations ? 1.5 : 1.0;
}

}  // namespace

StepResult StaticAnalysis::run_step(int step, const std::function<void(const std::string&)>& log) {
  prepare_step(step);
  if (step == 0) anchor_contacts();
  const StepDef& s = model_.steps[step];
  StepResult result;
  double time = 0.0, dt = s.initial_dt;
  double last_lambda_in_step = 0.0;  // the load fraction of the committed state within this step
  int previous_iterations = 0;       // Newton iterations of the last converged increment
  bool factorization_committed = false;  // the last factorization is Newton's last at the committed state
  const bool contact_in_step = std::any_of(s.loads.contact_active.begin(), s.loads.contact_active.end(),
                                           [](char active) { return active != 0; });
  bool moves_prescribed = !rigid_motions_.empty();
  for (const Ramp& r : prescribed_) moves_prescribed = moves_prescribed || r.start != r.end;
  const bool displacement_driven = moves_prescribed && !contact_in_step;
  const int n = system_->size();
  Eigen::VectorXd rhs(n), du(n);

  // The linear solve of one Newton correction: du of the free dofs for R + coupling, or false with a note.
  auto correction = [&](const Eigen::VectorXd& coupling, bool first_of_step, int it, IncrementRecord& rec,
                        Eigen::VectorXd& full) {
    for (int d = 0; d < n_dofs_; ++d)
      if (system_->equation(d) >= 0) rhs[system_->equation(d)] = -(residual_[d] + coupling[d]);
    if (!system_->finite()) {
      rec.note = "the tangent stiffness is not finite (an element's stiffness overflowed)";
      return false;
    }
    bool solved;
    {
      const ScopedTimer timer(timings_.factorization_s);
      const int reused_before = system_->reused_factorizations(), steps_before = system_->krylov_steps();
      solved = system_->solve(rhs, du, forcing_term(rec.residual_norms));
      timings_.krylov_steps += system_->krylov_steps() - steps_before;
      ++(system_->reused_factorizations() > reused_before ? timings_.reused_factorizations : timings_.factorizations);
    }
    if (system_->became_indefinite())
      log("step " + std::to_string(step + 1) + ": the tangent is not positive definite; UMFPACK LU solves it "
          "for the rest of the step");
    if (!solved) {
      if (first_of_step && it == 0)
        throw std::runtime_error("the tangent stiffness is singular at the start of step " + std::to_string(step + 1) +
                                 ": part of the model can move freely; fix rigid-body motions with *BOUNDARY");
      rec.note = "singular tangent (a structural instability?)";
      return false;
    }
    linear_solver_ = system_->solver_name();
    full.setZero(n_dofs_);
    for (int d = 0; d < n_dofs_; ++d)
      if (system_->equation(d) >= 0) full[d] = du[system_->equation(d)];
    return true;
  };

  // One Newton solve of the increment ending at load fraction lambda; u is updated in place. u starts at the
  // committed state, its prescribed dofs where the previous increment left them; prescribed_step moves them to
  // this increment's values. The first correction solves for the free dofs' response to that move, K_ff du_f =
  // -(R_f + K_fp du_p), with K_fp du_p the directional derivative of R along du_p (Wriggers, Nonlinear Finite
  // Element Methods, sec. 5.1): the boundary and the interior move together, so no row of elements next to the
  // boundary is squashed, and Newton converges quadratically from its first iteration.
  // The predictor's K_ff is the tangent at the committed state. After a converged increment the factorization
  // of Newton's last iteration is that tangent to within the last correction, and is reused: one factorization
  // less per increment. After a cut-back, or at a step's start, the tangent is assembled and factorized there.
  auto newton = [&](Eigen::VectorXd& u, double lambda, const Eigen::VectorXd& prescribed_step, IncrementRecord& rec,
                    bool first_of_step, bool committed_factorization) {
    const double largest_step = prescribed_step.cwiseAbs().maxCoeff();
    const bool reuse = largest_step > 0.0 && committed_factorization && system_->factorized();
    Evaluation ev = evaluate(u, lambda, !reuse);
    if (!ev.ok) {
      rec.note = "the residual at the start of the increment is not finite";
      return false;
    }
    // The force scale is at least the one the increment started from: a volume change or
    // an axial stretch of a free body, or a rigid motion, ends in a state where every
    // nodal force vanishes with the residual, which would then never be small relative
    // to the current forces alone.
    const double increment_reference = ev.reference;
    if (largest_step > 0.0) {
      const Eigen::VectorXd start_residual = residual_;
      const double h = kDirectionalStep * model_size_ / largest_step;
      const Evaluation shifted = evaluate(u + h * prescribed_step, lambda, false);
      if (!shifted.ok) {
        rec.note = "the residual next to the start of the increment is not finite";
        return false;
      }
      const Eigen::VectorXd coupling = (residual_ - start_residual) / h;
      residual_ = start_residual;
      Eigen::VectorXd full;
      if (reuse) {
        for (int d = 0; d < n_dofs_; ++d)
          if (system_->equation(d) >= 0) rhs[system_->equation(d)] = -(residual_[d] + coupling[d]);
        const ScopedTimer timer(timings_.factorization_s);
        if (!system_->solve_factored(rhs, du)) {
          rec.note = "the committed state's factorization gave no finite predictor";
          return false;
        }
        full.setZero(n_dofs_);
        for (int d = 0; d < n_dofs_; ++d)
          if (system_->equation(d) >= 0) full[d] = du[system_->equation(d)];
      } else if (!correction(coupling, first_of_step, 0, rec, full)) {
        return false;
      }
      u += prescribed_step + full;
      ev = evaluate(u, lambda, true);
      if (!ev.ok) {
        rec.note = "an element turned inside out (det F <= 0) under the prescribed displacement increment";
        return false;
      }
    }
    int rises = 0, releases = 0, round_start = 0;
    double last_correction = std::numeric_limits<double>::infinity();
    forget_contact_iterates();
    for (int it = 0;; ++it) {
      // Friction nodes that chatter between slip directions are held sticking (hold_chattering_contacts): the
      // residual at u changes with them.
      if (hold_chattering_contacts()) {
        ev = evaluate(u, lambda, true);
        if (!ev.ok) {
          rec.note = "residual not finite";
          return false;
        }
      }
      double relative = ev.norm / std::max(ev.reference, increment_reference);
      auto converged = [&] {
        return relative <= settings_.residual_tolerance ||
               (relative <= settings_.floor_tolerance &&
                last_correction <= settings_.correction_tolerance * std::max(u.cwiseAbs().maxCoeff(), 1e-300)) ||
               last_correction <= 1e-13 * model_size_;
      };
      // A converged state must obey Coulomb's law at the held nodes too; those it would let slip slip from now
      // on, and Newton iterates on from the residual with them slipping.
      if (converged() && release_slipping_contacts()) {
        if (++releases > kMaxSlipReleases) {
          rec.note = "more than " + std::to_string(kMaxSlipReleases) + " slip releases";
          return false;
        }
        ev = evaluate(u, lambda, true);
        relative = ev.norm / std::max(ev.reference, increment_reference);
        last_correction = std::numeric_limits<double>::infinity();
        round_start = it;
      }
      rec.residual_norms.push_back(relative);
      // Converged: the residual below the tolerance; or, as stiff penalties (contact) put a round-off floor
      // under the residual, a small residual with a negligible correction; or, in a state where every force is
      // round-off from the start (all nodes moved rigidly, only hybrid pressures free) and there is no force
      // scale at all, a correction at the round-off of the model's size: nothing is left to solve.
      if (converged()) return true;
      const bool out_of_iterations = it - round_start >= settings_.max_iterations;
      if (!std::isfinite(relative) || out_of_iterations) {
        rec.note = out_of_iterations ? "no convergence within the iteration limit" : "residual not finite";
        return false;
      }
      // The convergence-rate check of CalculiX and Abaqus (I_0 iterations): a displacement-driven increment
      // whose residual is still far from the quadratic regime after kRateCheckIterations is too large; cutting
      // it back costs less than iterating on
      if (displacement_driven && it - round_start >= kRateCheckIterations &&
          relative > kSlowContraction * rec.residual_norms[it - 1]) {
        rec.note = "converging slowly: a smaller increment";
        return false;
      }
      Eigen::VectorXd full;
      if (!correction(Eigen::VectorXd::Zero(n_dofs_), first_of_step && largest_step == 0.0, it, rec, full)) return false;

      Eigen::VectorXd trial = u;
      Evaluation next = line_search(trial, full, lambda, ev);
      if (!next.ok) {
        rec.note = "every line-search step turns an element inside out";
        return false;
      }
      last_correction = (trial - u).cwiseAbs().maxCoeff();
      rises = next.norm > ev.norm ? rises + 1 : 0;
      if (rises >= 6) {
        rec.note = "residual diverging";
        return false;
      }
      u = trial;
      ev = next;
    }
  };

  while (time < s.period * (1.0 - 1e-12)) {
    if (result.increments >= s.max_increments) {
      result.message = "reached the increment limit INC=" + std::to_string(s.max_increments) + " at step time " +
                       std::to_string(time) + "; raise INC on *STEP";
      return result;
    }
    if (s.period - (time + dt) < 1e-9 * s.period) dt = s.period - time;
    dt = std::min(dt, s.period - time);
    const double lambda = (time + dt) / s.period;
    IncrementRecord rec;
    rec.time = time + dt;
    rec.dt = dt;
    Eigen::VectorXd u = u_;
    apply_prescribed(u, last_lambda_in_step);
    Eigen::VectorXd target = u;
    apply_prescribed(target, lambda);
    rec.converged = newton(u, lambda, target - u, rec, time == 0.0 && result.cutbacks == 0, factorization_committed);
    forget_contact_iterates();  // later evaluations (output, sensitivities, the next increment) hold no node
    factorization_committed = rec.converged;
    result.records.push_back(rec);
    // An increment whose prescribed displacements invert an element stops before its first residual.
    const int iterations = std::max(static_cast<int>(rec.residual_norms.size()) - 1, 0);
    result.newton_iterations += iterations;
    std::ostringstream line;
    line << "step " << step + 1 << " time " << rec.time << " dt " << dt << ": " << iterations << " iterations, residual ";
    if (rec.residual_norms.empty())
      line << "none";
    else
      line << rec.residual_norms.back();
    line << (rec.converged ? "" : " (cut back: " + rec.note + ")");
    log(line.str());
    if (rec.converged) {
      u_ = u;
      last_lambda_ = lambda;
      if (carries_path_sensitivities_) propagate_path_sensitivities();
      for (ContactState& c : contacts_) c.history = c.trial;
      last_lambda_in_step = lambda;
      time += dt;
      result.time_reached = time;
      ++result.increments;
      dt = std::min(dt * next_increment_factor(iterations, previous_iterations, displacement_driven), s.max_dt);
      previous_iterations = iterations;
      continue;
    }
    ++result.cutbacks;
    previous_iterations = 0;
    dt *= 0.25;
    if (dt < s.min_dt * (1.0 - 1e-12)) {
      result.message = "increment below the minimum " + std::to_string(s.min_dt) + " at step time " +
                       std::to_string(time) + " (" + rec.note + ")";
      return result;
    }
  }
  result.converged = true;
  return result;
}

}  // namespace calfit
