// Node-to-segment contact: see node_to_segment.hpp.
#include "contact/node_to_segment.hpp"

#include <vector>

namespace calfit {

ContactPoint contact_element(const Eigen::VectorXd& x, const ContactLaw& law, const ContactHistory& history,
                             int segment, double weight, Eigen::VectorXd& r, Eigen::MatrixXd* K,
                             bool hold_stick, double offset) {
  const int n = static_cast<int>(x.size());
  const int n_nodes = n / 2;
  r.setZero(n);
  const ContactPoint point = contact_residual<double>(x.data(), n_nodes, law, history, segment, weight, r.data(),
                                                      hold_stick, nullptr, nullptr, offset);
  if (!K) return point;
  K->setZero(n, n);
  if (!point.touching) return point;
  constexpr double h = 1e-30;
  std::vector<std::complex<double>> xc(x.data(), x.data() + n), rc(n);
  for (int j = 0; j < n; ++j) {
    xc[j] += std::complex<double>(0.0, h);
    contact_residual<std::complex<double>>(xc.data(), n_nodes, law, history, segment, weight, rc.data(), hold_stick,
                                           nullptr, nullptr, std::complex<double>(offset));
    for (int i = 0; i < n; ++i) (*K)(i, j) = std::imag(rc[i]) / h;
    xc[j] = x[j];
  }
  return point;
}

ContactHistoryDerivatives contact_history_derivatives(const Eigen::VectorXd& x, const ContactLaw& law,
                                                      const ContactHistory& history, int segment, double weight,
                                                      double offset) {
  using C = std::complex<double>;
  constexpr double h = 1e-30;
  const int n = static_cast<int>(x.size());
  const int n_nodes = n / 2;
  ContactHistoryDerivatives out{Eigen::MatrixXd::Zero(n, 3), Eigen::MatrixXd::Zero(3, n), Eigen::MatrixXd::Zero(n, n),
                                Eigen::VectorXd::Zero(n), Eigen::Matrix3d::Zero(), Eigen::VectorXd::Zero(n),
                                Eigen::Vector3d::Zero()};
  contact_residual<double>(x.data(), n_nodes, law, history, segment, weight, out.r.data(), false, nullptr, nullptr, offset);
  const C at(offset);
  std::vector<C> xc(x.data(), x.data() + n), rc(n);
  const HistoryValues<C> base{history.xi, history.shear, history.gap};
  auto store = [&](const HistoryValues<C>& left, auto&& column) {
    column(0) = std::imag(left.xi) / h;
    column(1) = std::imag(left.shear) / h;
    column(2) = std::imag(left.gap) / h;
  };
  for (int j = 0; j < n; ++j) {  // d(residual, history left) / dx
    xc[j] += C(0.0, h);
    HistoryValues<C> left{};
    contact_residual(xc.data(), n_nodes, law, history, segment, weight, rc.data(), false, &base, &left, at);
    for (int i = 0; i < n; ++i) out.dr_dx(i, j) = std::imag(rc[i]) / h;
    store(left, out.dh_dx.col(j));
    xc[j] = x[j];
  }
  for (int k = 0; k < 3; ++k) {  // d(residual, history left) / d(history started from)
    HistoryValues<C> old = base, left{};
    (k == 0 ? old.xi : k == 1 ? old.shear : old.gap) += C(0.0, h);
    contact_residual(xc.data(), n_nodes, law, history, segment, weight, rc.data(), false, &old, &left, at);
    for (int i = 0; i < n; ++i) out.dr_dh(i, k) = std::imag(rc[i]) / h;
    store(left, out.dh_dh.col(k));
  }
  {  // d(residual, history left) / d(offset)
    HistoryValues<C> left{};
    contact_residual(xc.data(), n_nodes, law, history, segment, weight, rc.data(), false, &base, &left, at + C(0.0, h));
    for (int i = 0; i < n; ++i) out.dr_doffset(i) = std::imag(rc[i]) / h;
    store(left, out.dh_doffset);
  }
  return out;
}

}  // namespace calfit
