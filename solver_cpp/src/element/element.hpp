// The element interface of calfit-fe: an element owns its integration points and
// integrates its internal force and tangent from its local unknowns. Local unknowns
// are the nodal displacements (x, y per node, in node order), followed for hybrid
// elements by their pressure unknowns.
#pragma once

#include "material/material.hpp"

#include <Eigen/Dense>
#include <cmath>

namespace calfit {

constexpr int kMaxElementDofs = 15;  // T6 displacement (12) + P1 pressure (3)
using ElementVector = Eigen::Matrix<double, Eigen::Dynamic, 1, Eigen::ColMajor, kMaxElementDofs, 1>;
using ElementMatrix =
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::ColMajor, kMaxElementDofs, kMaxElementDofs>;
using NodeMatrix = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::ColMajor, 6, 2>;  // nodes x 2

// What the step imposes on an element besides its nodal unknowns: the kinematics of
// the project keywords *VOLUME CHANGE and *AXIAL STRETCH (solver_cpp/README.md).
//  - growth g: the multiplicative split F = F_e F_g with F_g = g I (3x3), g = (1 + dv)^(1/3),
//    of Rodriguez, Hoger & McCulloch (1994, J. Biomech. 27:455): the stress-free state of
//    the tissue has changed its volume by the factor 1 + dv. With W per reference volume
//    J_g W_e(C_e), C_e = C / g^2, the stress and tangent are S = g S_e(C / g^2) and
//    D = D_e(C / g^2) / g.
//  - axial_stretch lambda_z: generalized plane strain F33 = lambda_z (C33 = lambda_z^2);
//    the in-plane weak form per unit reference length is unchanged, J = lambda_z det F2.
// Both are 1 in plain plane strain. StaticAnalysis ramps them over the step.
struct ElementKinematics {
  double growth = 1.0;         // g
  double axial_stretch = 1.0;  // lambda_z
  static ElementKinematics from_volume_change(double dv, double axial_stretch) {
    return {std::cbrt(1.0 + dv), axial_stretch};
  }
};

// State at the integration points, for output.
struct ElementState {
  Mat3 cauchy = Mat3::Zero();  // volume average of the Cauchy stress
  double J = 1.0;              // volume average of det F
  double min_J = 1.0;
};

class Element {
public:
  virtual ~Element() = default;
  virtual int dof_count() const = 0;
  // Internal force f and, if K is given, its tangent dR/dlocal, at local unknowns ue
  // under the imposed kinematics kin. Returns false when det F <= 0 at an integration
  // point (the element turned inside out).
  virtual bool internal_force(const ElementVector& ue, const ElementKinematics& kin, ElementVector& f,
                              ElementMatrix* K) const = 0;
  virtual ElementState state(const ElementVector& ue, const ElementKinematics& kin) const = 0;
};

}  // namespace calfit
