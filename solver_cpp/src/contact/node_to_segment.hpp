// Penalty node-to-segment contact with Coulomb friction, in 2D (Wriggers, Computational
// Contact Mechanics, 2nd ed., sec. 9.1-9.2; the garment-skin contact of the second
// paper, sec. 2.5: penalty normal contact, friction coefficient mu).
//
// A slave node s of tributary length w meets a master segment (a, b). Faceted masters
// make the contact normal jump from one segment to the next, and Newton then chatters
// between them; the master is therefore given a continuous normal field, interpolated
// linearly from nodal normals n_a, n_b (each the normalized sum of the rotated adjacent
// segment vectors, rot(v) = (v_y, -v_x): outward for faces running counter-clockwise
// around their body): N(xi) = (1 - xi) n_a + xi n_b, with the contact point
// x_c = x_a + xi (x_b - x_a) solving (x_s - x_c) x N(xi) = 0 (a quadratic in xi, solved
// by Newton's method from the straight projection). Gap g = (x_s - x_c) . N / |N|,
// normal traction p_N = K <-g> (CalculiX PRESSURE-OVERCLOSURE=LINEAR, slope K).
// Friction: the slip increment is the tangential motion of the slave relative to the
// master material point it touched at the last converged state (segment o1-o2 at
// xi_n), dg_T = (x_s - x_o(xi_n)) . t, t = (-N_y, N_x)/|N|; trial traction
// t_T = t_T,n - lambda dg_T (lambda the stick slope), returned onto |t_T| <= mu p_N.
// First touch: a slave that was open at the last converged state (gap g_n >= 0, facing
// x_o(xi_n)) and penetrates now (g < 0) crossed the master at the fraction
// g_n / (g_n - g) of its relative motion (linear in the increment); only the rest,
// -g / (g_n - g) of dg_T, is slip under contact: dg_T = -g / (g_n - g) (x_s - x_o) . t
// from t_T,n = 0. Without it, the increment in which a node touches would be
// frictionless, and a band wrapping onto the skin within one or two increments (the
// garment deck's release) slides nearly freely: on the 2,000-element phantom leg the
// tissue moved by 48 um RMS between 5 and 80 release increments (5 um with it).
// The traction p_N n + t_T t acts on the slave, its opposite on a and b with weights
// (1 - xi, xi).
//
// The local residual is written once, templated on the scalar, and its exact tangent
// is obtained by complex-step differentiation (Squire & Trapp 1998): every operation
// is analytic where the contact state is fixed, and the state is decided on real parts.
#pragma once

#include <Eigen/Dense>
#include <complex>

namespace calfit {

struct ContactLaw {
  double penalty = 0;      // K: normal traction per unit overclosure
  double friction = 0;     // mu
  double stick_slope = 0;  // lambda: tangential traction per unit slip while sticking
};

// State of one slave node at the last converged increment. With friction, a node that
// does not touch but faces the master (projection near a segment, gap >= 0) keeps that
// projection and its gap, from which a first touch within the next increment is located
// (see below).
struct ContactHistory {
  bool touching = false;
  int segment = -1;   // master segment index (-1: none, no anchor)
  double xi = 0;      // master material coordinate on it
  double shear = 0;   // tangential traction t_T (0 while open)
  double gap = 0;     // open gap g_n >= 0 to that point, when not touching
  double slip = 0;    // the slave's tangential motion over the master since its first touch (signed, length)

  bool anchored() const { return segment >= 0; }
};

// Result of one slave node's contact for output and history update.
struct ContactPoint {
  bool touching = false;
  int segment = -1;
  double xi = 0, gap = 0, pressure = 0, shear = 0;
  int slip = 0;  // +1 / -1: slipping, the shear returned onto +mu p_N / -mu p_N; 0: sticking or open
  double tangential_motion = 0;  // with friction: the slave's motion along t over its anchor this increment
};

// Nodes of the local contact element, in this order: slave, a, b, the node before a
// on the master (a itself at an open end), the node after b (b itself at an open end),
// and, with friction and an anchor (ContactHistory::anchored), o1, o2 (the segment
// touched, or faced, at the last converged state). x: positions (2 per node); writes
// the residual r (2 per node).
constexpr int kContactNodes = 5, kFrictionNodes = 7;

// The continuous part of a slave node's history (ContactHistory's xi, shear and gap), in the scalar of the
// residual: the parameter sensitivities through friction (solver/sensitivity.hpp) differentiate the residual with
// respect to the history it started the increment from, and the history it leaves with respect to both.
template <typename T>
struct HistoryValues {
  T xi, shear, gap;
};

// hold_stick: the shear is the trial traction even outside the cone (ContactPoint::slip still says where the
// law would slip): Newton's iterates hold a node that chatters between slip directions there (see
// StaticAnalysis::contact_residual), and a converged state is accepted only if no held node lies outside it.
// `old`: the continuous history the residual uses (nullptr: the history's own values); `updated`: if not null, the
// continuous history the node leaves this state with (as StaticAnalysis::contact_residual records it: touching,
// the contact point and the shear, gap 0; open, the point it faces and its gap, shear 0). `offset`: how far the
// slave stands out from its position as the contact sees it (*GAP PROFILE; the gap is g - offset).
template <typename T>
ContactPoint contact_residual(const T* x, int n_nodes, const ContactLaw& law, const ContactHistory& history,
                              int segment, double weight, T* r, bool hold_stick = false,
                              const HistoryValues<T>* old = nullptr, HistoryValues<T>* updated = nullptr,
                              T offset = T(0)) {
  using std::sqrt;
  using V = Eigen::Matrix<T, 2, 1>;
  auto node = [&](int k) { return V(x[2 * k], x[2 * k + 1]); };
  // Eigen's dot() conjugates its left operand; the complex step needs the plain product.
  auto dot = [](const V& a, const V& b) { return T(a.x() * b.x() + a.y() * b.y()); };
  auto cross = [](const V& a, const V& b) { return T(a.x() * b.y() - a.y() * b.x()); };
  auto rot = [](const V& v) { return V(v.y(), -v.x()); };
  auto unit = [&](const V& v) { return V(v / sqrt(dot(v, v))); };
  for (int k = 0; k < 2 * n_nodes; ++k) r[k] = T(0);

  const V xs = node(0), xa = node(1), xb = node(2);
  const V d = xb - xa;
  const V na = unit(rot(xa - node(3)) + rot(d));
  const V nb = unit(rot(d) + rot(node(4) - xb));
  const V m = nb - na;
  const V rel = xs - xa;
  T xi = dot(rel, d) / dot(d, d);
  for (int it = 0; it < 8; ++it) {  // (rel - xi d) x (na + xi m) = 0
    const V arm = rel - xi * d, normal = na + xi * m;
    const T f = cross(arm, normal);
    const T df = cross(-d, normal) + cross(arm, m);
    xi -= f / df;
  }
  const V normal = na + xi * m;
  const V n = normal / sqrt(dot(normal, normal));
  const V t(-n.y(), n.x());
  const T gap = dot(rel - xi * d, n) - offset;

  ContactPoint out;
  out.segment = segment;
  out.xi = std::real(xi);
  out.gap = std::real(gap);
  if (updated) *updated = HistoryValues<T>{xi, T(0), gap};
  if (std::real(gap) >= 0.0 || std::real(xi) < -0.5 || std::real(xi) > 1.5) return out;
  out.touching = true;
  const T pressure = -law.penalty * gap;
  T shear(0);
  if (law.friction > 0.0 && history.anchored() && n_nodes == kFrictionNodes) {
    const HistoryValues<T> h = old ? *old : HistoryValues<T>{T(history.xi), T(history.shear), T(history.gap)};
    const V xo = (1.0 - h.xi) * node(5) + h.xi * node(6);
    T slip = dot(xs - xo, t);
    if (!history.touching) slip *= -gap / (h.gap - gap);  // slip since the first touch
    out.tangential_motion = std::real(slip);
    const T trial = h.shear - law.stick_slope * slip;
    const double limit = law.friction * std::real(pressure);
    if (std::abs(std::real(trial)) > limit) out.slip = std::real(trial) > 0 ? 1 : -1;
    if (out.slip == 0 || hold_stick) {
      shear = trial;
    } else {
      shear = out.slip * law.friction * pressure;
    }
  }
  out.pressure = std::real(pressure);
  out.shear = std::real(shear);
  if (updated) *updated = HistoryValues<T>{xi, shear, T(0)};
  // Traction on the slave; residual = -(force on the node).
  const V traction = (pressure * n + shear * t) * weight;
  r[0] -= traction.x();
  r[1] -= traction.y();
  r[2] += (1.0 - xi) * traction.x();
  r[3] += (1.0 - xi) * traction.y();
  r[4] += xi * traction.x();
  r[5] += xi * traction.y();
  return out;
}

// Residual and its exact tangent (complex step) for a local contact element; hold_stick: see contact_residual.
ContactPoint contact_element(const Eigen::VectorXd& x, const ContactLaw& law, const ContactHistory& history,
                             int segment, double weight, Eigen::VectorXd& r, Eigen::MatrixXd* K,
                             bool hold_stick = false, double offset = 0.0);

// How a local contact element at a converged state depends on the history it started from, and how the history
// it leaves depends on its positions and on that history (complex step, every entry exact): the chain that carries
// parameter sensitivities through Coulomb friction from one increment to the next (StaticAnalysis::
// propagate_path_sensitivities). Columns and rows of the history are (xi, shear, gap). With the slave's offset
// (*GAP PROFILE) as well: how the residual and the history left depend on it (the *SENSITIVITY GAP PROFILE lines),
// and the residual on the positions (what a SHAPE parameter moves).
struct ContactHistoryDerivatives {
  Eigen::MatrixXd dr_dh;  // 2 n_nodes x 3: the local residual
  Eigen::MatrixXd dh_dx;  // 3 x 2 n_nodes: the history left
  Eigen::MatrixXd dr_dx;  // 2 n_nodes x 2 n_nodes: the local residual at the history started from
  Eigen::VectorXd r;      // the local residual itself (linear in the slave's weight)
  Eigen::Matrix3d dh_dh = Eigen::Matrix3d::Zero();
  Eigen::VectorXd dr_doffset;  // 2 n_nodes
  Eigen::Vector3d dh_doffset = Eigen::Vector3d::Zero();
};
ContactHistoryDerivatives contact_history_derivatives(const Eigen::VectorXd& x, const ContactLaw& law,
                                                      const ContactHistory& history, int segment, double weight,
                                                      double offset = 0.0);

}  // namespace calfit
