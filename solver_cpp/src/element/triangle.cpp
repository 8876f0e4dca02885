// Triangle interpolation and quadrature (see triangle.hpp). Quadrature: centroid rule,
// the 3-point interior rule of degree 2 (Strang & Fix), and Dunavant's 6-point rule
// of degree 4 (Dunavant 1985, IJNME 21:1129, table for p = 4).
#include "element/triangle.hpp"

#include <cmath>
#include <stdexcept>

namespace calfit {

int node_count(ElementShape shape) { return shape == ElementShape::T3 ? 3 : 6; }
int edge_node_count(ElementShape shape) { return shape == ElementShape::T3 ? 2 : 3; }

const std::vector<QuadraturePoint>& triangle_rule(int degree) {
  static const std::vector<QuadraturePoint> one = {{1.0 / 3.0, 1.0 / 3.0, 0.5}};
  static const std::vector<QuadraturePoint> three = {
      {1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0}, {2.0 / 3.0, 1.0 / 6.0, 1.0 / 6.0}, {1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0}};
  static const std::vector<QuadraturePoint> six = [] {
    const double a = 0.445948490915965, wa = 0.223381589678011 / 2.0;
    const double b = 0.091576213509771, wb = 0.109951743655322 / 2.0;
    return std::vector<QuadraturePoint>{{a, a, wa}, {1 - 2 * a, a, wa}, {a, 1 - 2 * a, wa},
                                        {b, b, wb}, {1 - 2 * b, b, wb}, {b, 1 - 2 * b, wb}};
  }();
  switch (degree) {
    case 1: return one;
    case 2: return three;
    case 4: return six;
    default: throw std::invalid_argument("triangle_rule: degree must be 1, 2 or 4");
  }
}

void shape_functions(ElementShape shape, double xi, double eta, Eigen::VectorXd& N, Eigen::MatrixXd& dN) {
  const double L1 = 1.0 - xi - eta, L2 = xi, L3 = eta;
  if (shape == ElementShape::T3) {
    N.resize(3);
    dN.resize(3, 2);
    N << L1, L2, L3;
    dN << -1, -1, 1, 0, 0, 1;
    return;
  }
  N.resize(6);
  dN.resize(6, 2);
  N << L1 * (2 * L1 - 1), L2 * (2 * L2 - 1), L3 * (2 * L3 - 1), 4 * L1 * L2, 4 * L2 * L3, 4 * L3 * L1;
  // d/dxi and d/deta with dL1 = (-1, -1), dL2 = (1, 0), dL3 = (0, 1).
  dN << -(4 * L1 - 1), -(4 * L1 - 1),  //
      4 * L2 - 1, 0,                   //
      0, 4 * L3 - 1,                   //
      4 * (L1 - L2), -4 * L2,          //
      4 * L3, 4 * L2,                  //
      -4 * L3, 4 * (L1 - L3);
}

std::vector<int> face_nodes(ElementShape shape, int face) {
  const int a = face, b = (face + 1) % 3;
  if (shape == ElementShape::T3) return {a, b};
  return {a, face + 3, b};
}

void edge_shape_functions(int n_nodes, double s, double* N, double* dN) {
  if (n_nodes == 2) {
    N[0] = 1.0 - s;
    N[1] = s;
    dN[0] = -1.0;
    dN[1] = 1.0;
    return;
  }
  N[0] = (1.0 - s) * (1.0 - 2.0 * s);
  N[1] = 4.0 * s * (1.0 - s);
  N[2] = s * (2.0 * s - 1.0);
  dN[0] = 4.0 * s - 3.0;
  dN[1] = 4.0 - 8.0 * s;
  dN[2] = 4.0 * s - 1.0;
}

const std::vector<std::array<double, 2>>& edge_rule(int n_points) {
  static const std::vector<std::array<double, 2>> two = [] {
    const double g = 0.5 / std::sqrt(3.0);
    return std::vector<std::array<double, 2>>{{0.5 - g, 0.5}, {0.5 + g, 0.5}};
  }();
  static const std::vector<std::array<double, 2>> three = [] {
    const double g = 0.5 * std::sqrt(0.6);
    return std::vector<std::array<double, 2>>{{0.5 - g, 5.0 / 18.0}, {0.5, 8.0 / 18.0}, {0.5 + g, 5.0 / 18.0}};
  }();
  if (n_points == 2) return two;
  if (n_points == 3) return three;
  throw std::invalid_argument("edge_rule: 2 or 3 points");
}

}  // namespace calfit
