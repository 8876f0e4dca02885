// Element and load unit tests: element tangent against central finite differences of
// the element residual (T3, T6, both rules, CPE3H, CPE6H; in plane strain and with a
// growth eigenstrain g != 1 and an axial stretch lambda_z != 1), the force as the
// gradient of the element energy g^3 W(C / g^2), no force in the grown stress-free state
// F = g I, zero residual under rigid motion,
// objectivity of the internal force, load stiffness of the follower pressure (uniform and
// interpolated from nodal pressures), of the Laplace-law membrane and of the garment's mixed
// load (membrane plus nodal follower pressure, REFERENCE=alpha) against finite differences,
// the nodal follower pressure at uniform values against the uniform one, the garment's load
// at alpha = 0 against the membrane load to the bit, and p = T/R on a circle.
#include "check.hpp"
#include "contact/node_to_segment.hpp"
#include "element/mixed_element.hpp"
#include "element/solid_element.hpp"
#include "load/edge_loads.hpp"
#include "material/laws.hpp"

#include <cmath>
#include <memory>

using namespace calfit;

namespace {

const double kPi = std::acos(-1.0);

NodeMatrix reference_nodes(ElementShape shape) {
  NodeMatrix X(node_count(shape), 2);
  X.topRows(3) << 0.1, 0.2, 1.3, 0.1, 0.4, 1.1;
  if (shape == ElementShape::T6) {
    X.row(3) = 0.5 * (X.row(0) + X.row(1)) + Eigen::RowVector2d(0.02, -0.03);  // curved edge
    X.row(4) = 0.5 * (X.row(1) + X.row(2));
    X.row(5) = 0.5 * (X.row(2) + X.row(0));
  }
  return X;
}

NodeMatrix some_displacement(int n) {
  NodeMatrix u(n, 2);
  for (int a = 0; a < n; ++a) u.row(a) << 0.05 * std::sin(1.0 + a), 0.04 * std::cos(2.0 * a);
  return u;
}

// Local unknowns: interleaved nodal displacements, then `pressures`.
ElementVector unknowns(const NodeMatrix& u, const Eigen::VectorXd& pressures = Eigen::VectorXd()) {
  ElementVector ue(2 * u.rows() + pressures.size());
  for (Eigen::Index a = 0; a < u.rows(); ++a) ue.segment<2>(2 * a) = u.row(a).transpose();
  ue.tail(pressures.size()) = pressures;
  return ue;
}

const ElementKinematics kPlaneStrain{};
// Drainage-like shrink of the stress-free state (dv = -0.12) with an axial stretch.
const ElementKinematics kGrownStretched = ElementKinematics::from_volume_change(-0.12, 1.07);
// Swelling (dv = +0.2) with an axial shortening.
const ElementKinematics kSwollenShortened = ElementKinematics::from_volume_change(0.2, 0.93);

// Tangent = d f / d(local unknowns) by central differences.
void check_tangent(const Element& element, const ElementVector& ue, const ElementKinematics& kin = kPlaneStrain) {
  ElementVector f;
  ElementMatrix K;
  CHECK(element.internal_force(ue, kin, f, &K));
  const double h = 1e-6;
  double worst = 0.0;
  for (int b = 0; b < element.dof_count(); ++b) {
    ElementVector up = ue, um = ue;
    up[b] += h;
    um[b] -= h;
    ElementVector fp, fm;
    element.internal_force(up, kin, fp, nullptr);
    element.internal_force(um, kin, fm, nullptr);
    worst = std::max(worst, ((fp - fm) / (2 * h) - K.col(b)).cwiseAbs().maxCoeff());
  }
  if (worst > 1e-6 * K.cwiseAbs().maxCoeff())
    std::cerr << "tangent off by " << worst << " (g " << kin.growth << ", lambda_z " << kin.axial_stretch << ")\n";
  CHECK(worst <= 1e-6 * K.cwiseAbs().maxCoeff());
  CHECK((K - K.transpose()).cwiseAbs().maxCoeff() <= 1e-10 * K.cwiseAbs().maxCoeff());  // hyperelastic: symmetric
}

// Central differences of an element energy E(ue) against the force f(ue), over the
// displacement unknowns.
template <typename Energy>
void check_force_gradient(const Element& element, const ElementVector& ue, const ElementKinematics& kin,
                          int n_displacement_dofs, Energy energy) {
  ElementVector f;
  CHECK(element.internal_force(ue, kin, f, nullptr));
  const double h = 1e-6;
  double worst = 0.0;
  for (int b = 0; b < n_displacement_dofs; ++b) {
    ElementVector up = ue, um = ue;
    up[b] += h;
    um[b] -= h;
    worst = std::max(worst, std::abs((energy(up) - energy(um)) / (2 * h) - f[b]));
  }
  if (worst > 1e-7 * f.cwiseAbs().maxCoeff()) std::cerr << "force vs energy gradient off by " << worst << '\n';
  CHECK(worst <= 1e-7 * f.cwiseAbs().maxCoeff());
}

// The displacement element's force is the gradient of sum_q w_q g^3 W(C_q / g^2): this
// checks the factor g of S = g S_e(C / g^2), which the tangent test cannot see.
void force_is_energy_gradient(const Element& element, const Material& material, const NodeMatrix& X, double thickness,
                              int degree, const ElementVector& ue, const ElementKinematics& kin) {
  const ElementShape shape = X.rows() == 3 ? ElementShape::T3 : ElementShape::T6;
  const std::vector<ReferencePoint> points = reference_points(shape, X, thickness, degree, nullptr);
  const double g = kin.growth;
  check_force_gradient(element, ue, kin, 2 * static_cast<int>(X.rows()), [&](const ElementVector& v) {
    const NodeMatrix u = nodal_displacements(v, static_cast<int>(X.rows()));
    double W = 0.0;
    for (const ReferencePoint& p : points)
      W += p.weight * g * g * g *
           material.energy(right_cauchy_green(deformation_gradient(u, p.dN_dX), kin.axial_stretch) / (g * g));
    return W;
  });
}

// The mixed element's displacement residual is the u-gradient of
// sum_q w_q [g^3 W_iso(C_q / g^2) + p_q J_q] (the -g^3 G(p) term does not depend on u).
void mixed_isochoric_force_is_energy_gradient(const Element& element, const SplitHyperelastic& material,
                                              const NodeMatrix& X, double thickness, int degree,
                                              const ElementVector& ue, const ElementKinematics& kin) {
  const ElementShape shape = X.rows() == 3 ? ElementShape::T3 : ElementShape::T6;
  const std::vector<ReferencePoint> points = reference_points(shape, X, thickness, degree, nullptr);
  const int n = static_cast<int>(X.rows());
  const double g = kin.growth;
  check_force_gradient(element, ue, kin, 2 * n, [&](const ElementVector& v) {
    const NodeMatrix u = nodal_displacements(v, n);
    const Eigen::VectorXd pressures = v.tail(element.dof_count() - 2 * n);
    double W = 0.0;
    for (const ReferencePoint& q : points) {
      const Eigen::Matrix2d F = deformation_gradient(u, q.dN_dX);
      const Mat3 Ce = right_cauchy_green(F, kin.axial_stretch) / (g * g);
      const double Je = std::sqrt(Ce.determinant());
      const double I1 = Ce.trace(), I2 = 0.5 * (I1 * I1 - (Ce * Ce).trace());
      const double iso = material.isochoric().evaluate(I1 * std::pow(Je, -2.0 / 3.0), I2 * std::pow(Je, -4.0 / 3.0)).W;
      const double p = pressures.size() == 3 ? q.L.dot(pressures) : pressures[0];
      W += q.weight * (g * g * g * iso + p * kin.axial_stretch * F.determinant());
    }
    return W;
  });
}

// F = g I in the plane with lambda_z = g is the grown, stress-free state F_e = I: no
// force (and, at p = 0, no volume-constraint residual: J = g^3 = g^3 Theta(0)).
void grown_state_is_stress_free(const Element& element, const NodeMatrix& X, int n_pressures) {
  const double g = kGrownStretched.growth;
  const ElementKinematics kin{g, g};
  ElementVector f;
  CHECK(element.internal_force(unknowns((g - 1.0) * X, Eigen::VectorXd::Zero(n_pressures)), kin, f, nullptr));
  CHECK(f.cwiseAbs().maxCoeff() <= 1e-14);
  // ... while in plane strain (lambda_z = 1) the same in-plane state is stressed.
  CHECK(element.internal_force(unknowns((g - 1.0) * X, Eigen::VectorXd::Zero(n_pressures)), ElementKinematics{g, 1.0}, f,
                               nullptr));
  CHECK(f.cwiseAbs().maxCoeff() > 1e-3);
}

void mixed_element_tests(const SplitHyperelastic& material, ElementShape shape, int degree) {
  const NodeMatrix X = reference_nodes(shape);
  const MixedElement element(shape, X, material, 1.3, degree);
  const int n = node_count(shape);
  Eigen::VectorXd p(element.pressure_count());
  for (int k = 0; k < p.size(); ++k) p[k] = 0.3 - 0.2 * k;
  for (const ElementKinematics& kin : {kPlaneStrain, kGrownStretched, kSwollenShortened})
    check_tangent(element, unknowns(some_displacement(n), p), kin);
  mixed_isochoric_force_is_energy_gradient(element, material, X, 1.3, degree, unknowns(some_displacement(n), p),
                                           kGrownStretched);
  grown_state_is_stress_free(element, X, element.pressure_count());
  // Rigid motion at zero pressure: no force and no volume-constraint residual.
  Eigen::Matrix2d R;
  R << std::cos(0.4), -std::sin(0.4), std::sin(0.4), std::cos(0.4);
  NodeMatrix rigid(n, 2);
  for (int a = 0; a < n; ++a) rigid.row(a) = (R * X.row(a).transpose() - X.row(a).transpose()).transpose();
  ElementVector f;
  CHECK(element.internal_force(unknowns(rigid, Eigen::VectorXd::Zero(p.size())), kPlaneStrain, f, nullptr));
  CHECK(f.cwiseAbs().maxCoeff() <= 1e-12);
  // A constant pressure p0 in the undeformed element: Cauchy stress p0 I (plus nothing
  // isochoric), so the element's written pressure -tr(sigma)/3 is -p0.
  const ElementState s =
      element.state(unknowns(NodeMatrix::Zero(n, 2), Eigen::VectorXd::Constant(p.size(), 0.7)), kPlaneStrain);
  CHECK_NEAR(-s.cauchy.trace() / 3.0, -0.7, 1e-12);
}

void element_tests(const Material& material, ElementShape shape, int degree) {
  const NodeMatrix X = reference_nodes(shape);
  const SolidElement element(shape, X, material, 1.7, degree);
  const int n = node_count(shape);
  const NodeMatrix u = some_displacement(n);
  ElementVector f;
  ElementMatrix K;
  CHECK(element.internal_force(unknowns(u), kPlaneStrain, f, &K));
  for (const ElementKinematics& kin : {kPlaneStrain, kGrownStretched, kSwollenShortened}) {
    check_tangent(element, unknowns(u), kin);
    force_is_energy_gradient(element, material, X, 1.7, degree, unknowns(u), kin);
  }
  grown_state_is_stress_free(element, X, 0);

  // Rigid motion: rotation by 0.7 rad and translation give no internal force.
  Eigen::Matrix2d R;
  R << std::cos(0.7), -std::sin(0.7), std::sin(0.7), std::cos(0.7);
  NodeMatrix rigid(n, 2);
  for (int a = 0; a < n; ++a) rigid.row(a) = (R * X.row(a).transpose() - X.row(a).transpose()).transpose() +
                                             Eigen::RowVector2d(0.3, -0.2);
  ElementVector f_rigid;
  CHECK(element.internal_force(unknowns(rigid), kPlaneStrain, f_rigid, nullptr));
  CHECK(f_rigid.cwiseAbs().maxCoeff() <= 1e-12 * std::max(1.0, f.cwiseAbs().maxCoeff()));

  // Objectivity: x -> R x rotates every nodal force by R.
  NodeMatrix rotated(n, 2);
  for (int a = 0; a < n; ++a)
    rotated.row(a) = (R * (X.row(a) + u.row(a)).transpose()).transpose() - X.row(a);
  ElementVector f_rot;
  CHECK(element.internal_force(unknowns(rotated), kPlaneStrain, f_rot, nullptr));
  double off = 0.0;
  for (int a = 0; a < n; ++a) off = std::max(off, (f_rot.segment<2>(2 * a) - R * f.segment<2>(2 * a)).cwiseAbs().maxCoeff());
  CHECK(off <= 1e-10 * f.cwiseAbs().maxCoeff());
}

template <typename Load>
void edge_stiffness_test(int n_nodes, Load load) {
  EdgeNodes x(n_nodes, 2);
  if (n_nodes == 2) {
    x << 0.0, 0.0, 1.0, 0.3;
  } else {
    x << 0.0, 0.0, 0.55, 0.25, 1.0, 0.3;
  }
  EdgeVector f;
  EdgeMatrix df;
  load(x, f, &df);
  const double h = 1e-7;
  double worst = 0.0;
  for (int b = 0; b < 2 * n_nodes; ++b) {
    EdgeNodes xp = x, xm = x;
    xp(b / 2, b % 2) += h;
    xm(b / 2, b % 2) -= h;
    EdgeVector fp, fm;
    load(xp, fp, nullptr);
    load(xm, fm, nullptr);
    worst = std::max(worst, ((fp - fm) / (2 * h) - df.col(b)).cwiseAbs().maxCoeff());
  }
  CHECK(worst <= 1e-6 * std::max(1.0, df.cwiseAbs().maxCoeff()));
}

// A circle of radius R split into quadratic arcs: the Laplace load's nodal pressure
// (force / consistent length along the normal) tends to T / R.
double circle_pressure_error(int n_faces, double R, double T) {
  const int n_nodes = 2 * n_faces;
  std::vector<Eigen::Vector2d> x(n_nodes);
  for (int k = 0; k < n_nodes; ++k) x[k] = R * Eigen::Vector2d(std::cos(2 * kPi * k / n_nodes), std::sin(2 * kPi * k / n_nodes));
  std::vector<Eigen::Vector2d> force(n_nodes, Eigen::Vector2d::Zero());
  std::vector<double> length(n_nodes, 0.0);
  for (int face = 0; face < n_faces; ++face) {
    const int ids[3] = {2 * face, 2 * face + 1, (2 * face + 2) % n_nodes};
    EdgeNodes xe(3, 2);
    for (int k = 0; k < 3; ++k) xe.row(k) = x[ids[k]].transpose();
    EdgeVector fe;
    laplace_membrane_load(xe, Eigen::Vector3d::Constant(T), fe, nullptr);
    Eigen::VectorXd w;
    EdgeNodes nw;
    face_weights(xe, w, nw);
    for (int k = 0; k < 3; ++k) {
      force[ids[k]] += fe.segment<2>(2 * k);
      length[ids[k]] += w[k];
    }
  }
  double worst = 0.0;
  for (int k = 0; k < n_nodes; ++k) {
    const double p = -force[k].dot(x[k].normalized()) / length[k];
    worst = std::max(worst, std::abs(p - T / R) / (T / R));
  }
  return worst;
}

// Contact: the complex-step tangent against central differences, for a penetrating
// slave node, frictionless and sticking / slipping with friction, after a converged
// contact or touching for the first time (open at the last converged state).
void contact_tests() {
  ContactLaw law{1e3, 0.0, 0.0};
  Eigen::VectorXd x(14);
  // Master segment (0,0)-(1,0.1): outward normal n = (t_y, -t_x), about (0.1, -1), so
  // the master body lies above the segment (y = 0.04 at x = 0.4): a slave at y = 0.06
  // penetrates, one at y = -0.02 is outside.
  // Nodes: slave, a, b, before a, after b, and the previously touched segment o1, o2.
  x << 0.4, 0.06, 0.0, 0.0, 1.0, 0.1, -0.8, 0.05, 1.9, 0.35, -0.05, 0.0, 0.95, 0.1;
  // Variants 5 and 6: the slipping ones (1 and 3) held sticking, as Newton holds a node that reversed its slip.
  for (int variant = 0; variant < 7; ++variant) {
    ContactHistory h;
    int n = 10;
    const bool hold = variant >= 5;
    const int base = hold ? 2 * variant - 9 : variant;
    if (base > 0) {
      // a stiff stick slope takes the trial traction out of the cone (slip), a soft one leaves it inside (stick)
      law = ContactLaw{1e3, 0.3, base % 2 == 1 ? 1e4 : 10.0};
      h = base <= 2 ? ContactHistory{true, 0, 0.35, 2.0} : ContactHistory{false, 0, 0.35, 0.0, 0.02};
      n = 14;
    }
    const Eigen::VectorXd xe = x.head(n);
    Eigen::VectorXd r;
    Eigen::MatrixXd K;
    const ContactPoint p = contact_element(xe, law, h, 0, 0.2, r, &K, hold);
    CHECK(p.touching);
    CHECK(p.gap < 0.0);
    const double step = 1e-7;
    double worst = 0.0;
    for (int j = 0; j < n; ++j) {
      Eigen::VectorXd xp = xe, xm = xe, rp, rm;
      xp[j] += step;
      xm[j] -= step;
      contact_element(xp, law, h, 0, 0.2, rp, nullptr, hold);
      contact_element(xm, law, h, 0, 0.2, rm, nullptr, hold);
      worst = std::max(worst, ((rp - rm) / (2 * step) - K.col(j)).cwiseAbs().maxCoeff());
    }
    if (worst > 1e-5 * K.cwiseAbs().maxCoeff()) std::cerr << "contact tangent off by " << worst << " variant " << variant << '\n';
    CHECK(worst <= 1e-5 * K.cwiseAbs().maxCoeff());
    if (base > 0) {  // the friction branch taken: slip at mu p, stick below it
      if (base % 2 == 1 && !hold) CHECK(std::abs(std::abs(p.shear) - 0.3 * p.pressure) < 1e-12 * p.pressure);
      if (base % 2 == 0) CHECK(std::abs(p.shear) < 0.3 * p.pressure && p.slip == 0);
      CHECK(p.shear != 0.0);
      CHECK((p.slip != 0) == (base % 2 == 1));
    }
    if (hold) {  // held: the trial traction, outside the cone, in the direction the law would slip
      Eigen::VectorXd free_r;
      const ContactPoint slipping = contact_element(xe, law, h, 0, 0.2, free_r, nullptr);
      CHECK(std::abs(p.shear) > 0.3 * p.pressure);
      CHECK(p.slip == slipping.slip && p.shear * slipping.shear > 0.0);
    }
    // Action and reaction: the contact forces sum to zero.
    double sum_x = 0.0, sum_y = 0.0;
    for (int k = 0; k < n / 2; ++k) {
      sum_x += r[2 * k];
      sum_y += r[2 * k + 1];
    }
    CHECK(std::abs(sum_x) < 1e-12 && std::abs(sum_y) < 1e-12);
  }
  // A slave outside the master body carries no force.
  Eigen::VectorXd outside(10), r;
  outside << 0.4, -0.02, 0.0, 0.0, 1.0, 0.1, -0.8, 0.05, 1.9, 0.35;
  CHECK(!contact_element(outside, ContactLaw{1e3, 0, 0}, ContactHistory{}, 0, 0.2, r, nullptr).touching);
  CHECK(r.cwiseAbs().maxCoeff() == 0.0);
}

// The garment's face loads (edge_loads.hpp): tangents of the nodal follower pressure and of the mixed load
// against central differences; a uniform nodal pressure is the uniform follower pressure; an all-zero reference
// pressure leaves the membrane load as it is, to the bit (REFERENCE=0 is today's load).
void garment_load_tests() {
  for (int n : {2, 3}) {
    Eigen::VectorXd nodal(n), tension(n);
    for (int k = 0; k < n; ++k) {
      nodal[k] = 0.5 + 0.3 * k * k;  // a pressure that varies along the face
      tension[k] = 0.2 + 0.1 * k;
    }
    edge_stiffness_test(n, [&](const EdgeNodes& x, EdgeVector& f, EdgeMatrix* df) { nodal_follower_pressure_load(x, nodal, f, df); });
    edge_stiffness_test(n, [&](const EdgeNodes& x, EdgeVector& f, EdgeMatrix* df) {
      garment_load(x, 0.6 * tension, 0.4 * nodal, f, df);
    });

    EdgeNodes x(n, 2);
    if (n == 2) {
      x << 0.1, -0.2, 1.2, 0.4;
    } else {
      x << 0.1, -0.2, 0.65, 0.1, 1.2, 0.4;  // straight, the mid-side node at the middle
    }
    EdgeVector f_uniform, f_nodal;
    EdgeMatrix df_uniform, df_nodal;
    follower_pressure_load(x, 0.7, f_uniform, &df_uniform);
    nodal_follower_pressure_load(x, Eigen::VectorXd::Constant(n, 0.7), f_nodal, &df_nodal);
    CHECK((f_nodal - f_uniform).cwiseAbs().maxCoeff() <= 1e-15 * f_uniform.cwiseAbs().maxCoeff());
    CHECK((df_nodal - df_uniform).cwiseAbs().maxCoeff() <= 1e-15 * df_uniform.cwiseAbs().maxCoeff());
    // The interpolated pressure's resultant is -integral p(xi) n ds: on a straight face n ds is the chord
    // rotated, times dxi, so it is -(the nodal pressures' mean with the weights integral N_a dxi: 1/2 1/2,
    // or 1/6 4/6 1/6) times the rotated chord.
    const Eigen::Vector2d chord = (x.row(n - 1) - x.row(0)).transpose();
    const double mean = n == 2 ? 0.5 * (nodal[0] + nodal[1]) : (nodal[0] + 4.0 * nodal[1] + nodal[2]) / 6.0;
    nodal_follower_pressure_load(x, nodal, f_nodal, nullptr);
    Eigen::Vector2d resultant = Eigen::Vector2d::Zero();
    for (int a = 0; a < n; ++a) resultant += f_nodal.segment<2>(2 * a);
    CHECK((resultant + mean * Eigen::Vector2d(chord.y(), -chord.x())).norm() <= 1e-14 * mean * chord.norm());

    EdgeVector f_membrane, f_garment;
    EdgeMatrix df_membrane, df_garment;
    laplace_membrane_load(x, tension, f_membrane, &df_membrane);
    garment_load(x, tension, Eigen::VectorXd::Zero(n), f_garment, &df_garment);
    CHECK(f_garment == f_membrane);
    CHECK(df_garment == df_membrane);
  }
}

}  // namespace

int main() {
  contact_tests();
  const SplitHyperelastic neo_hooke(std::make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0, 0.3}),
                                    std::make_shared<PolynomialVolumetric>(std::vector<double>{0.1}));
  const StVenantKirchhoff svk(5.0, 0.3);
  for (const Material* m : {static_cast<const Material*>(&neo_hooke), static_cast<const Material*>(&svk)}) {
    element_tests(*m, ElementShape::T3, 1);
    element_tests(*m, ElementShape::T6, 2);
    element_tests(*m, ElementShape::T6, 4);
  }
  const SplitHyperelastic nearly_incompressible(
      std::make_shared<MooneyRivlinIsochoric>(0.8, 0.2), std::make_shared<PolynomialVolumetric>(std::vector<double>{0.01}));
  const SplitHyperelastic incompressible(std::make_shared<MooneyRivlinIsochoric>(0.8, 0.2),
                                         std::make_shared<PolynomialVolumetric>(std::vector<double>{0.0}));
  const SplitHyperelastic avril(std::make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0}),
                                std::make_shared<LogVolumetric>(50.0));
  for (const SplitHyperelastic* m : {&nearly_incompressible, &incompressible, &avril}) {
    mixed_element_tests(*m, ElementShape::T3, 1);
    mixed_element_tests(*m, ElementShape::T6, 2);
    mixed_element_tests(*m, ElementShape::T6, 4);
  }
  for (int n : {2, 3}) {
    edge_stiffness_test(n, [](const EdgeNodes& x, EdgeVector& f, EdgeMatrix* df) { follower_pressure_load(x, 0.7, f, df); });
    edge_stiffness_test(n, [n](const EdgeNodes& x, EdgeVector& f, EdgeMatrix* df) {
      Eigen::VectorXd T(n);
      for (int k = 0; k < n; ++k) T[k] = 0.2 + 0.1 * k;  // a tension profile
      laplace_membrane_load(x, T, f, df);
    });
  }
  garment_load_tests();
  // Pressure T/R on a circle, converging with refinement.
  const double coarse = circle_pressure_error(16, 50.0, 0.16), fine = circle_pressure_error(64, 50.0, 0.16);
  std::cout << "Laplace p vs T/R, relative error: 16 faces " << coarse << ", 64 faces " << fine << '\n';
  CHECK(fine < 1e-3);
  CHECK(fine < coarse);
  return calfit::testing::tally().finish();
}
