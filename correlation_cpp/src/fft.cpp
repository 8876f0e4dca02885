#include "fft.hpp"

#include <cmath>
#include <stdexcept>

namespace calfit::correlation {

std::size_t next_power_of_two(std::size_t n) {
  std::size_t p = 1;
  while (p < n) p <<= 1;
  return p;
}

Fft::Fft(std::size_t n) : n_(n), reversed_(n), twiddles_(n / 2), column_(n) {
  if (n == 0 || (n & (n - 1)) != 0) throw std::invalid_argument("the FFT's size must be a power of two");
  std::size_t bits = 0;
  while ((std::size_t{1} << bits) < n) ++bits;
  for (std::size_t i = 0; i < n; ++i) {
    std::size_t r = 0;
    for (std::size_t b = 0; b < bits; ++b) r |= ((i >> b) & 1u) << (bits - 1 - b);
    reversed_[i] = r;
  }
  const double pi = std::acos(-1.0);
  // each twiddle from its own angle, not by repeated multiplication, whose rounding grows with n
  for (std::size_t k = 0; k < n / 2; ++k) {
    const double angle = -2.0 * pi * static_cast<double>(k) / static_cast<double>(n);
    twiddles_[k] = {std::cos(angle), std::sin(angle)};
  }
}

void Fft::transform(std::complex<double>* data, bool inverse) const {
  for (std::size_t i = 0; i < n_; ++i)
    if (i < reversed_[i]) std::swap(data[i], data[reversed_[i]]);
  for (std::size_t length = 2; length <= n_; length <<= 1) {
    const std::size_t half = length / 2, stride = n_ / length;
    for (std::size_t start = 0; start < n_; start += length) {
      for (std::size_t j = 0; j < half; ++j) {
        const std::complex<double> w = inverse ? std::conj(twiddles_[j * stride]) : twiddles_[j * stride];
        const std::complex<double> u = data[start + j], v = data[start + j + half] * w;
        data[start + j] = u + v;
        data[start + j + half] = u - v;
      }
    }
  }
}

void Fft::transform_2d(std::vector<std::complex<double>>& grid, bool inverse) {
  for (std::size_t row = 0; row < n_; ++row) transform(grid.data() + row * n_, inverse);
  for (std::size_t col = 0; col < n_; ++col) {
    for (std::size_t row = 0; row < n_; ++row) column_[row] = grid[row * n_ + col];
    transform(column_.data(), inverse);
    for (std::size_t row = 0; row < n_; ++row) grid[row * n_ + col] = column_[row];
  }
}

}  // namespace calfit::correlation
