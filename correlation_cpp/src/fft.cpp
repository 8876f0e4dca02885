#include "fft.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace calfit::correlation {

std::size_t next_power_of_two(std::size_t n) {
  std::size_t p = 1;
  while (p < n) p <<= 1;
  return p;
}

Fft::Fft(std::size_t n) : n_(n), reversed_(n), twiddles_(n / 2) {
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

// The butterflies multiply in real arithmetic: std::complex's operator* checks for infinities and NaN (C99 Annex G)
// through a library call per product, which made the transform several times slower.
void Fft::transform(std::complex<double>* data, bool inverse) const {
  for (std::size_t i = 0; i < n_; ++i)
    if (i < reversed_[i]) std::swap(data[i], data[reversed_[i]]);
  const double sign = inverse ? -1.0 : 1.0;
  for (std::size_t length = 2; length <= n_; length <<= 1) {
    const std::size_t half = length / 2, stride = n_ / length;
    for (std::size_t start = 0; start < n_; start += length) {
      for (std::size_t j = 0; j < half; ++j) {
        const double wr = twiddles_[j * stride].real(), wi = sign * twiddles_[j * stride].imag();
        std::complex<double>& a = data[start + j];
        std::complex<double>& b = data[start + j + half];
        const double vr = b.real() * wr - b.imag() * wi, vi = b.real() * wi + b.imag() * wr;
        const double ur = a.real(), ui = a.imag();
        a = {ur + vr, ui + vi};
        b = {ur - vr, ui - vi};
      }
    }
  }
}

void Fft::transform_2d(std::vector<std::complex<double>>& grid, bool inverse) {
  // rows, a transpose, rows: the columns' transforms read contiguous memory; the result is transposed (module text)
  for (std::size_t row = 0; row < n_; ++row) transform(grid.data() + row * n_, inverse);
  constexpr std::size_t block = 16;
  for (std::size_t r0 = 0; r0 < n_; r0 += block)
    for (std::size_t c0 = r0; c0 < n_; c0 += block)
      for (std::size_t r = r0; r < std::min(r0 + block, n_); ++r)
        for (std::size_t c = (c0 == r0 ? r + 1 : c0); c < std::min(c0 + block, n_); ++c)
          std::swap(grid[r * n_ + c], grid[c * n_ + r]);
  for (std::size_t row = 0; row < n_; ++row) transform(grid.data() + row * n_, inverse);
}

}  // namespace calfit::correlation
