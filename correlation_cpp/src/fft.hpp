// A radix-2 complex FFT, enough for the windows' integer search: the search patch and the template are correlated
// through their spectra, as skimage's match_template does with scipy's FFT, because a direct sum over every shift
// costs (3 W)^2 W^2 products (150 million for a 64-pixel window) where the transform costs some 10 million.
#pragma once

#include <complex>
#include <cstddef>
#include <vector>

namespace calfit::correlation {

class Fft {
 public:
  // n: the side of the square grids transformed, a power of two (`next_power_of_two`).
  explicit Fft(std::size_t n);

  std::size_t size() const { return n_; }

  // The 2-D transform of an n x n row-major grid in place, unnormalised (the inverse does not divide by n^2), and
  // transposed: element (i, j) holds frequency (j, i). A forward and an inverse transform in turn give the grid back
  // in its own orientation, and a product of two spectra is taken element by element, so the correlation, the one
  // use, never transposes back.
  void transform_2d(std::vector<std::complex<double>>& grid, bool inverse);

 private:
  void transform(std::complex<double>* data, bool inverse) const;

  std::size_t n_;
  std::vector<std::size_t> reversed_;                  // the bit-reversed index of each position
  std::vector<std::complex<double>> twiddles_;         // exp(-2 pi i k / n), k < n / 2
};

std::size_t next_power_of_two(std::size_t n);

}  // namespace calfit::correlation
