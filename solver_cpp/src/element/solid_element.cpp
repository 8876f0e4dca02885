// Plane-strain total Lagrangian element: see solid_element.hpp for the equations.
#include "element/solid_element.hpp"

namespace calfit {
namespace {

// Voigt positions of the in-plane components 11, 22, 12 in the 6x6 tangent.
constexpr int kPlane[3] = {0, 1, 3};

// B of the Green-Lagrange strain's variation, dE = B du (Voigt 11, 22, 2 x 12): B_a = [F_i1 g1; F_i2 g2; F_i1 g2 +
// F_i2 g1] for node a's gradient (g1, g2), in a fixed- or a dynamic-size matrix.
template <typename Gradients, typename Operator>
void fill_strain_operator(const Eigen::Matrix2d& F, const Gradients& dN, Operator& B) {
  for (int a = 0; a < static_cast<int>(dN.rows()); ++a) {
    const double g1 = dN(a, 0), g2 = dN(a, 1);
    for (int i = 0; i < 2; ++i) {
      B(0, 2 * a + i) = F(i, 0) * g1;
      B(1, 2 * a + i) = F(i, 1) * g2;
      B(2, 2 * a + i) = F(i, 0) * g2 + F(i, 1) * g1;
    }
  }
}

// The element kernels for N nodes, in fixed-size matrices: with the dynamic sizes of ElementMatrix, w B^T D B
// (12 x 3 x 12 for a T6) went through Eigen's general matrix product (packing, blocking), a sixth of the 22.5k-DOF
// calf's tangent evaluations.
template <int N>
void add_tangent_fixed(const ReferencePoint& p, const Eigen::Matrix2d& F, const Mat3& S, const Mat6& D,
                       ElementMatrix& K) {
  const Eigen::Matrix<double, N, 2> dN = p.dN_dX;
  Eigen::Matrix<double, 3, 2 * N> B;
  fill_strain_operator(F, dN, B);
  Eigen::Matrix3d D3;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) D3(r, c) = p.weight * D(kPlane[r], kPlane[c]);
  const Eigen::Matrix<double, 3, 2 * N> DB = D3 * B;
  Eigen::Matrix<double, 2 * N, 2 * N> Kp = B.transpose().lazyProduct(DB);  // coefficient-wise, not a GEMM
  const Eigen::Matrix<double, N, N> G = dN * (p.weight * S.topLeftCorner<2, 2>()) * dN.transpose();
  for (int b = 0; b < N; ++b)
    for (int a = 0; a < N; ++a) {  // the geometric stiffness couples like components only
      Kp(2 * a, 2 * b) += G(a, b);
      Kp(2 * a + 1, 2 * b + 1) += G(a, b);
    }
  K.template topLeftCorner<2 * N, 2 * N>() += Kp;
}

template <int N>
bool internal_force_fixed(const std::vector<ReferencePoint>& points, const Material& material, const ElementVector& ue,
                          const ElementKinematics& kin, ElementVector& f, ElementMatrix* K) {
  const Eigen::Map<const Eigen::Matrix<double, 2, N>> u(ue.data());  // column a: node a's (u_x, u_y)
  Eigen::Matrix<double, 2, N> forces = Eigen::Matrix<double, 2, N>::Zero();
  if (K) K->setZero(2 * N, 2 * N);
  const auto elastic = [&material](const Mat3& C, Mat3& S, Mat6* D) { material.stress(C, S, D); };
  Mat3 S;
  Mat6 D;
  for (const ReferencePoint& p : points) {
    const Eigen::Matrix<double, N, 2> dN = p.dN_dX;
    const Eigen::Matrix2d F = Eigen::Matrix2d::Identity() + u * dN;
    if (F.determinant() <= 0.0) return false;
    stress_with_growth(elastic, right_cauchy_green(F, kin.axial_stretch), kin.growth, S, K ? &D : nullptr);
    const Eigen::Matrix2d P = p.weight * (F * S.topLeftCorner<2, 2>());
    forces.noalias() += P * dN.transpose();
    if (K) add_tangent_fixed<N>(p, F, S, D, *K);
  }
  f = Eigen::Map<const Eigen::Matrix<double, 2 * N, 1>>(forces.data());
  return true;
}

}  // namespace

std::vector<ReferencePoint> reference_points(ElementShape shape, const NodeMatrix& X, double thickness,
                                             int quadrature_degree, double* min_det) {
  Eigen::VectorXd N;
  Eigen::MatrixXd dN;
  std::vector<ReferencePoint> points;
  for (const QuadraturePoint& q : triangle_rule(quadrature_degree)) {
    shape_functions(shape, q.xi, q.eta, N, dN);
    const Eigen::Matrix2d J0 = X.transpose() * dN;  // dX/dxi
    const double det = J0.determinant();
    if (min_det) *min_det = points.empty() ? det : std::min(*min_det, det);
    ReferencePoint p;
    p.dN_dX = dN * J0.inverse();
    p.L << 1.0 - q.xi - q.eta, q.xi, q.eta;
    p.weight = q.weight * det * thickness;
    points.push_back(p);
  }
  return points;
}

Eigen::Matrix2d deformation_gradient(const NodeMatrix& u, const NodeMatrix& dN_dX) {
  return Eigen::Matrix2d::Identity() + u.transpose() * dN_dX;
}

Mat3 right_cauchy_green(const Eigen::Matrix2d& F, double axial_stretch) {
  Mat3 C = Mat3::Zero();
  C.topLeftCorner<2, 2>() = F.transpose() * F;
  C(2, 2) = axial_stretch * axial_stretch;
  return C;
}

Eigen::Matrix<double, 3, Eigen::Dynamic, Eigen::RowMajor, 3, 12> strain_operator(const Eigen::Matrix2d& F,
                                                                                 const NodeMatrix& dN_dX) {
  Eigen::Matrix<double, 3, Eigen::Dynamic, Eigen::RowMajor, 3, 12> B(3, 2 * static_cast<int>(dN_dX.rows()));
  fill_strain_operator(F, dN_dX, B);
  return B;
}

void add_displacement_tangent(const ReferencePoint& p, const Eigen::Matrix2d& F, const Mat3& S, const Mat6& D,
                              ElementMatrix& K) {
  if (p.dN_dX.rows() == 6) {
    add_tangent_fixed<6>(p, F, S, D, K);
  } else {
    add_tangent_fixed<3>(p, F, S, D, K);
  }
}

NodeMatrix nodal_displacements(const ElementVector& ue, int n_nodes) {
  NodeMatrix u(n_nodes, 2);
  for (int a = 0; a < n_nodes; ++a) u.row(a) << ue[2 * a], ue[2 * a + 1];
  return u;
}

SolidElement::SolidElement(ElementShape shape, const NodeMatrix& X, const Material& material, double thickness,
                           int quadrature_degree)
    : shape_(shape), material_(&material), points_(reference_points(shape, X, thickness, quadrature_degree, &min_det_)) {}

double SolidElement::reference_area() const {
  double area = 0.0;
  for (const ReferencePoint& p : points_) area += p.weight;
  return area;
}

bool SolidElement::internal_force(const ElementVector& ue, const ElementKinematics& kin, ElementVector& f,
                                  ElementMatrix* K) const {
  if (shape_ == ElementShape::T6) return internal_force_fixed<6>(points_, *material_, ue, kin, f, K);
  return internal_force_fixed<3>(points_, *material_, ue, kin, f, K);
}

ElementState SolidElement::state(const ElementVector& ue, const ElementKinematics& kin) const {
  const auto elastic = [this](const Mat3& C, Mat3& S, Mat6* D) { material_->stress(C, S, D); };
  return average_state(points_, nodal_displacements(ue, node_count(shape_)), kin.axial_stretch,
                       [&](const ReferencePoint&, const Mat3& C) {
                         Mat3 S;
                         stress_with_growth(elastic, C, kin.growth, S, nullptr);
                         return S;
                       });
}

}  // namespace calfit
