// Penalty node-to-segment contact with Coulomb friction, in 2D (Wriggers, Computational
// Contact Mechanics, 2nd ed., sec. 9.1-9.2; the garment-skin contact of the second
// paper, sec. 2.5: penalty normal contact, friction coefficient mu).
//
// A slave node s of tributary length w meets a straight master segment (m1, m2) with
// unit tangent t = (x2 - x1)/L and outward normal n = (t_y, -t_x) (master faces run
// counter-clockwise around their body). Gap g = (x_s - x1) . n, projection
// xi = (x_s - x1) . t / L. Normal traction p_N = K <-g> (CalculiX PRESSURE-OVERCLOSURE=
// LINEAR with slope K). Friction: the slip increment is the tangential motion of the
// slave relative to the master material point it touched at the last converged state
// (segment o1-o2 at xi_n), dg_T = (x_s - x_o(xi_n)) . t; trial traction
// t_T = t_T,n - lambda dg_T (lambda the stick slope), returned onto |t_T| <= mu p_N.
// The traction p_N n + t_T t acts on the slave and its opposite on the master,
// distributed with (1 - xi, xi).
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

// State of one slave node at the last converged increment.
struct ContactHistory {
  bool touching = false;
  int segment = -1;   // master segment index
  double xi = 0;      // master material coordinate on it
  double shear = 0;   // tangential traction t_T
};

// Result of one slave node's contact for output and history update.
struct ContactPoint {
  bool touching = false;
  int segment = -1;
  double xi = 0, gap = 0, pressure = 0, shear = 0;
};

// Nodes of the local contact element: slave, m1, m2 and, with friction, o1, o2 (the
// segment touched at the last converged state; may coincide with m1, m2).
// x: positions (2 per node). Writes the residual contribution r (2 per node).
template <typename T>
ContactPoint contact_residual(const T* x, int n_nodes, const ContactLaw& law, const ContactHistory& history,
                              int segment, double weight, T* r) {
  using std::sqrt;
  using V = Eigen::Matrix<T, 2, 1>;
  auto node = [&](int k) { return V(x[2 * k], x[2 * k + 1]); };
  // Eigen's dot() conjugates its left operand; the complex step needs the plain product.
  auto dot = [](const V& a, const V& b) { return T(a.x() * b.x() + a.y() * b.y()); };
  const V xs = node(0), x1 = node(1), x2 = node(2);
  const V d = x2 - x1;
  const T length = sqrt(dot(d, d));
  const V t = d / length;
  const V n(t.y(), -t.x());
  const T gap = dot(xs - x1, n);
  const T xi = dot(xs - x1, t) / length;
  for (int k = 0; k < 2 * n_nodes; ++k) r[k] = T(0);

  ContactPoint out;
  out.segment = segment;
  out.xi = std::real(xi);
  out.gap = std::real(gap);
  if (std::real(gap) >= 0.0) return out;
  out.touching = true;
  const T pressure = -law.penalty * gap;
  T shear(0);
  if (law.friction > 0.0 && history.touching && n_nodes == 5) {
    const V xo = (1.0 - history.xi) * node(3) + history.xi * node(4);
    const T trial = history.shear - law.stick_slope * dot(xs - xo, t);
    const double limit = law.friction * std::real(pressure);
    if (std::abs(std::real(trial)) <= limit) {
      shear = trial;
    } else {
      shear = (std::real(trial) > 0 ? 1.0 : -1.0) * law.friction * pressure;
    }
  }
  out.pressure = std::real(pressure);
  out.shear = std::real(shear);
  // Traction on the slave; residual = -(force on the node).
  const V traction = (pressure * n + shear * t) * weight;
  const T xi_c = std::real(xi) < 0 ? T(0) : (std::real(xi) > 1 ? T(1) : xi);
  r[0] -= traction.x();
  r[1] -= traction.y();
  r[2] += (1.0 - xi_c) * traction.x();
  r[3] += (1.0 - xi_c) * traction.y();
  r[4] += xi_c * traction.x();
  r[5] += xi_c * traction.y();
  return out;
}

// Residual and its exact tangent (complex step) for a local contact element.
ContactPoint contact_element(const Eigen::VectorXd& x, const ContactLaw& law, const ContactHistory& history,
                             int segment, double weight, Eigen::VectorXd& r, Eigen::MatrixXd* K);

}  // namespace calfit
