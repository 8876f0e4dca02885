// The element interface of calfit-fe: an element owns its integration points and
// integrates its internal force and tangent from its local unknowns. Local unknowns
// are the nodal displacements (x, y per node, in node order), followed for hybrid
// elements by their pressure unknowns.
#pragma once

#include "material/material.hpp"

#include <Eigen/Dense>

namespace calfit {

constexpr int kMaxElementDofs = 15;  // T6 displacement (12) + P1 pressure (3)
using ElementVector = Eigen::Matrix<double, Eigen::Dynamic, 1, Eigen::ColMajor, kMaxElementDofs, 1>;
using ElementMatrix =
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::ColMajor, kMaxElementDofs, kMaxElementDofs>;
using NodeMatrix = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::ColMajor, 6, 2>;  // nodes x 2

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
  // Internal force f and, if K is given, its tangent dR/dlocal, at local unknowns ue.
  // Returns false when det F <= 0 at an integration point (the element turned inside out).
  virtual bool internal_force(const ElementVector& ue, ElementVector& f, ElementMatrix* K) const = 0;
  virtual ElementState state(const ElementVector& ue) const = 0;
};

}  // namespace calfit
