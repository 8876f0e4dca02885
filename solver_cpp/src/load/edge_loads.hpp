// Loads on element faces (edges in 2D), integrated on the CURRENT configuration.
//
// Follower pressure p (force per unit deformed length, positive into the body):
//   f_a = -p integral N_a n ds = -p integral N_a (x'_y, -x'_x) ds,
// n the outward normal of a counter-clockwise element face, x' = dx/ds; its
// derivative (load stiffness) is df_a/dx_b = integral N_a N_b' ds [[0, -p], [p, 0]]
// (Bonet & Wood eq. 8.43 in 2D).
//
// Laplace law, p = T / r (Avril et al. 2010, eq. 1): the normal load of a membrane of
// tension T(s) lying on the face,
//   f_a = -integral (T N_a)' t ds,  t = x' / |x'|,
// which integrates by parts to integral T N_a kappa n ds (the pressure T kappa = T / r
// along the inward normal) plus the kink forces T (t+ - t-) at element corners, so
// curvature is taken from the deformed geometry with no separate fitting. Tangent:
//   df_a/dx_b = -integral (T N_a)' (I - t t^T) / |x'| N_b' ds.
// For constant T it is the gradient of -T x (length): a conservative, symmetric load.
//
// Follower pressure with nodal values p_a, interpolated along the face, p(xi) = sum_c N_c p_c
// (the reference-curvature garment law, *LAPLACE PRESSURE with REFERENCE=alpha > 0):
//   f_a = -integral N_a p(xi) n ds,   df_a/dx_b = integral p(xi) N_a N_b' dxi [[0, -1], [1, 0]],
// from n ds = (x'_y, -x'_x) dxi, whose derivative with respect to x_b is N_b' [[0, 1], [-1, 0]] dxi.
// Uniform p_a = p gives follower_pressure_load's load up to round-off.
#pragma once

#include <Eigen/Dense>

namespace calfit {

using EdgeNodes = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::ColMajor, 3, 2>;        // nodes x 2
using EdgeVector = Eigen::Matrix<double, Eigen::Dynamic, 1, Eigen::ColMajor, 6, 1>;
using EdgeMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::ColMajor, 6, 6>;

// x: current positions of the face's nodes, ordered along the face (2 or 3 nodes).
void follower_pressure_load(const EdgeNodes& x, double pressure, EdgeVector& f, EdgeMatrix* df_dx);

// nodal_pressure: p_a at the face's nodes (force per unit deformed length, positive into the body).
void nodal_follower_pressure_load(const EdgeNodes& x, const Eigen::VectorXd& nodal_pressure, EdgeVector& f,
                                  EdgeMatrix* df_dx);

// tension: nodal membrane tension (force per unit length) at the face's nodes.
void laplace_membrane_load(const EdgeNodes& x, const Eigen::VectorXd& tension, EdgeVector& f, EdgeMatrix* df_dx);

// The garment of *LAPLACE PRESSURE with REFERENCE=alpha on one face: f = (1 - alpha) f_deformed + alpha
// f_reference, given as tension = (1 - alpha) T (laplace_membrane_load) and reference_pressure = alpha p0
// (nodal_follower_pressure_load; p0 from the reference contour, see StaticAnalysis::reference_pressures).
// An all-zero reference_pressure adds nothing, not even round-off: alpha = 0 is the membrane load alone.
void garment_load(const EdgeNodes& x, const Eigen::VectorXd& tension, const Eigen::VectorXd& reference_pressure,
                  EdgeVector& f, EdgeMatrix* df_dx);

// Consistent nodal length weights integral N_a ds and normal sums integral N_a n ds
// of a face, to turn nodal forces into nodal pressures for output.
void face_weights(const EdgeNodes& x, Eigen::VectorXd& length_weight, EdgeNodes& normal_weight);

}  // namespace calfit
