// Triangle and edge interpolation of calfit-fe: T3 (linear) and T6 (quadratic)
// Lagrange triangles in area coordinates L1 = 1 - xi - eta, L2 = xi, L3 = eta,
// with the node order of CalculiX/Abaqus (corners 1-3 counter-clockwise, mid-side
// nodes 4: 1-2, 5: 2-3, 6: 3-1), and the Gauss rules used on them.
#pragma once

#include <Eigen/Dense>
#include <array>
#include <vector>

namespace calfit {

enum class ElementShape { T3, T6 };

int node_count(ElementShape shape);
int edge_node_count(ElementShape shape);  // nodes on one face: 2 or 3

struct QuadraturePoint {
  double xi, eta, weight;  // weights sum to 1/2, the reference triangle's area
};
// degree 1 (1 point), 2 (3 points) or 4 (6 points, Dunavant).
const std::vector<QuadraturePoint>& triangle_rule(int degree);

// Shape functions N (n) and derivatives dN/d(xi, eta) (n x 2) at (xi, eta).
void shape_functions(ElementShape shape, double xi, double eta, Eigen::VectorXd& N, Eigen::MatrixXd& dN);

// Local node indices of face 0..2 in order along the edge: corner k, [mid-side], corner k+1.
std::vector<int> face_nodes(ElementShape shape, int face);

// 1D Lagrange functions on s in [0, 1] for an edge of 2 or 3 nodes (order: start,
// [middle], end) and their derivatives d/ds.
void edge_shape_functions(int n_nodes, double s, double* N, double* dN);
// Gauss-Legendre points on [0, 1]: 2 or 3 points.
const std::vector<std::array<double, 2>>& edge_rule(int n_points);

}  // namespace calfit
