// Face loads: see edge_loads.hpp for the equations.
#include "load/edge_loads.hpp"

#include "element/triangle.hpp"

namespace calfit {
namespace {

struct EdgePoint {
  double N[3], dN[3], weight;
};

// 3 Gauss points integrate every edge integrand here exactly or to the order of the
// element (degree <= 5 for T6 faces under a follower pressure, constant or interpolated
// from the nodes: N_a p(xi) x' is of degree 2 + 2 + 1).
template <typename Fn>
void for_each_point(int n, Fn&& fn) {
  for (const auto& g : edge_rule(3)) {
    EdgePoint p;
    edge_shape_functions(n, g[0], p.N, p.dN);
    p.weight = g[1];
    fn(p);
  }
}

// f_a = -integral N_a p(xi) n ds and its derivative (edge_loads.hpp); pressure_at(point) gives p(xi).
template <typename PressureAt>
void follower_load(const EdgeNodes& x, PressureAt&& pressure_at, EdgeVector& f, EdgeMatrix* df_dx) {
  const int n = static_cast<int>(x.rows());
  f.setZero(2 * n);
  if (df_dx) df_dx->setZero(2 * n, 2 * n);
  for_each_point(n, [&](const EdgePoint& p) {
    Eigen::Vector2d dx = Eigen::Vector2d::Zero();
    for (int b = 0; b < n; ++b) dx += p.dN[b] * x.row(b).transpose();
    const Eigen::Vector2d n_ds(dx.y(), -dx.x());  // outward normal times ds/dxi
    const double pressure = pressure_at(p);
    for (int a = 0; a < n; ++a) {
      f.segment<2>(2 * a) -= p.weight * pressure * p.N[a] * n_ds;
      if (!df_dx) continue;
      for (int b = 0; b < n; ++b) {
        const double c = p.weight * pressure * p.N[a] * p.dN[b];
        (*df_dx)(2 * a, 2 * b + 1) -= c;
        (*df_dx)(2 * a + 1, 2 * b) += c;
      }
    }
  });
}

}  // namespace

void follower_pressure_load(const EdgeNodes& x, double pressure, EdgeVector& f, EdgeMatrix* df_dx) {
  follower_load(x, [pressure](const EdgePoint&) { return pressure; }, f, df_dx);
}

void nodal_follower_pressure_load(const EdgeNodes& x, const Eigen::VectorXd& nodal_pressure, EdgeVector& f,
                                  EdgeMatrix* df_dx) {
  const int n = static_cast<int>(x.rows());
  follower_load(
      x,
      [&](const EdgePoint& p) {
        double pressure = 0.0;
        for (int c = 0; c < n; ++c) pressure += p.N[c] * nodal_pressure(c);
        return pressure;
      },
      f, df_dx);
}

void laplace_membrane_load(const EdgeNodes& x, const Eigen::VectorXd& tension, EdgeVector& f, EdgeMatrix* df_dx) {
  const int n = static_cast<int>(x.rows());
  f.setZero(2 * n);
  if (df_dx) df_dx->setZero(2 * n, 2 * n);
  for_each_point(n, [&](const EdgePoint& p) {
    Eigen::Vector2d dx = Eigen::Vector2d::Zero();
    double T = 0.0, dT = 0.0;
    for (int b = 0; b < n; ++b) {
      dx += p.dN[b] * x.row(b).transpose();
      T += p.N[b] * tension(b);
      dT += p.dN[b] * tension(b);
    }
    const double length = dx.norm();
    const Eigen::Vector2d t = dx / length;
    const Eigen::Matrix2d projector = (Eigen::Matrix2d::Identity() - t * t.transpose()) / length;
    for (int a = 0; a < n; ++a) {
      const double TN_a = dT * p.N[a] + T * p.dN[a];  // (T N_a)'
      f.segment<2>(2 * a) -= p.weight * TN_a * t;
      if (!df_dx) continue;
      for (int b = 0; b < n; ++b)
        df_dx->block<2, 2>(2 * a, 2 * b) -= p.weight * TN_a * p.dN[b] * projector;
    }
  });
}

void garment_load(const EdgeNodes& x, const Eigen::VectorXd& tension, const Eigen::VectorXd& reference_pressure,
                  EdgeVector& f, EdgeMatrix* df_dx) {
  laplace_membrane_load(x, tension, f, df_dx);
  if ((reference_pressure.array() == 0.0).all()) return;
  EdgeVector f_reference;
  EdgeMatrix df_reference;
  nodal_follower_pressure_load(x, reference_pressure, f_reference, df_dx ? &df_reference : nullptr);
  f += f_reference;
  if (df_dx) *df_dx += df_reference;
}

void face_weights(const EdgeNodes& x, Eigen::VectorXd& length_weight, EdgeNodes& normal_weight) {
  const int n = static_cast<int>(x.rows());
  length_weight.setZero(n);
  normal_weight.setZero(n, 2);
  for_each_point(n, [&](const EdgePoint& p) {
    Eigen::Vector2d dx = Eigen::Vector2d::Zero();
    for (int b = 0; b < n; ++b) dx += p.dN[b] * x.row(b).transpose();
    const Eigen::Vector2d n_ds(dx.y(), -dx.x());
    for (int a = 0; a < n; ++a) {
      length_weight(a) += p.weight * p.N[a] * dx.norm();
      normal_weight.row(a) += p.weight * p.N[a] * n_ds.transpose();
    }
  });
}

}  // namespace calfit
