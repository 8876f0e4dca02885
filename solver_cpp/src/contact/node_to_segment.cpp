// Node-to-segment contact: see node_to_segment.hpp.
#include "contact/node_to_segment.hpp"

#include <vector>

namespace calfit {

ContactPoint contact_element(const Eigen::VectorXd& x, const ContactLaw& law, const ContactHistory& history,
                             int segment, double weight, Eigen::VectorXd& r, Eigen::MatrixXd* K,
                             bool hold_stick) {
  const int n = static_cast<int>(x.size());
  const int n_nodes = n / 2;
  r.setZero(n);
  const ContactPoint point = contact_residual(x.data(), n_nodes, law, history, segment, weight, r.data(), hold_stick);
  if (!K) return point;
  K->setZero(n, n);
  if (!point.touching) return point;
  constexpr double h = 1e-30;
  std::vector<std::complex<double>> xc(x.data(), x.data() + n), rc(n);
  for (int j = 0; j < n; ++j) {
    xc[j] += std::complex<double>(0.0, h);
    contact_residual(xc.data(), n_nodes, law, history, segment, weight, rc.data(), hold_stick);
    for (int i = 0; i < n; ++i) (*K)(i, j) = std::imag(rc[i]) / h;
    xc[j] = x[j];
  }
  return point;
}

}  // namespace calfit
