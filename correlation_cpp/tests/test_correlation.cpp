// The DIC windows' hot loops (correlation_cpp/src/windows.hpp) on inputs whose answer is known, and on inputs that
// must be refused or rejected rather than read out of bounds: tiny images, windows at and beyond the border, NaN.
// orchestrator's tests/measure/test_compiled_windows.py holds the loops to the Python reference on the phantom.
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <stdexcept>
#include <vector>

#include "../../solver_cpp/tests/check.hpp"
#include "fft.hpp"
#include "windows.hpp"

using namespace calfit::correlation;

namespace {

// A smooth random texture: a sum of a few sinusoids, so that its spline coefficients can simply be the image itself
// (the loops take any coefficients; the test needs only a deformed image that is the reference moved).
double texture(double row, double col) {
  return 100.0 + 20.0 * std::sin(0.31 * col + 0.2 * row) + 15.0 * std::cos(0.23 * row - 0.11 * col) +
         10.0 * std::sin(0.07 * col * 1.3 + 0.41 * row);
}

struct Scene {
  std::ptrdiff_t rows, cols;
  std::vector<double> reference, deformed, grad_rows, grad_cols;
  Pair pair() const {
    Pair p;
    p.reference = {reference.data(), rows, cols};
    p.spline = {deformed.data(), rows, cols};
    p.grad_rows = {grad_rows.data(), rows, cols};
    p.grad_cols = {grad_cols.data(), rows, cols};
    p.to_deformed = {1, 0, 0, 0, 1, 0};
    return p;
  }
};

// the reference and the same texture moved by (shift_col, shift_row): the deformed image at x is I0(x - shift)
Scene scene(std::ptrdiff_t rows, std::ptrdiff_t cols, double shift_col, double shift_row) {
  Scene s{rows, cols, {}, {}, {}, {}};
  for (std::ptrdiff_t r = 0; r < rows; ++r)
    for (std::ptrdiff_t c = 0; c < cols; ++c) {
      const double y = static_cast<double>(r), x = static_cast<double>(c);
      s.reference.push_back(texture(y, x));
      s.deformed.push_back(texture(y - shift_row, x - shift_col));
      s.grad_rows.push_back((texture(y + 1e-4, x) - texture(y - 1e-4, x)) / 2e-4);
      s.grad_cols.push_back((texture(y, x + 1e-4) - texture(y, x - 1e-4)) / 2e-4);
    }
  return s;
}

void test_fft_round_trip_and_correlation() {
  std::mt19937 random(3);
  std::normal_distribution<double> normal;
  const std::ptrdiff_t p = 20, w = 6;
  std::vector<double> patch(p * p), tmpl(w * w);
  for (double& v : patch) v = normal(random);
  for (std::ptrdiff_t r = 0; r < w; ++r)
    for (std::ptrdiff_t c = 0; c < w; ++c) tmpl[r * w + c] = patch[(r + 5) * p + c + 9];
  const std::vector<double> score = zncc_map(patch, p, tmpl, w);
  const std::ptrdiff_t m = p - w + 1;
  CHECK(score.size() == static_cast<std::size_t>(m * m));
  CHECK_NEAR(score[5 * m + 9], 1.0, 1e-12);   // the template where it was cut out
  // every score against the direct sum
  double worst = 0.0;
  for (std::ptrdiff_t i = 0; i < m; ++i)
    for (std::ptrdiff_t j = 0; j < m; ++j) {
      double tm = 0, pm = 0;
      for (std::ptrdiff_t r = 0; r < w; ++r)
        for (std::ptrdiff_t c = 0; c < w; ++c) {
          tm += tmpl[r * w + c];
          pm += patch[(i + r) * p + j + c];
        }
      tm /= static_cast<double>(w * w);
      pm /= static_cast<double>(w * w);
      double num = 0, tt = 0, pp = 0;
      for (std::ptrdiff_t r = 0; r < w; ++r)
        for (std::ptrdiff_t c = 0; c < w; ++c) {
          const double a = tmpl[r * w + c] - tm, b = patch[(i + r) * p + j + c] - pm;
          num += a * b;
          tt += a * a;
          pp += b * b;
        }
      worst = std::max(worst, std::abs(score[i * m + j] - num / std::sqrt(tt * pp)));
    }
  CHECK(worst < 1e-12);
  // a flat patch scores 0, not NaN
  const std::vector<double> flat = zncc_map(std::vector<double>(p * p, 7.0), p, tmpl, w);
  bool zeros = true;
  for (double v : flat) zeros = zeros && v == 0.0;
  CHECK(zeros);
  bool refused = false;
  try {
    zncc_map(patch, w - 1, tmpl, w);
  } catch (const std::invalid_argument&) {
    refused = true;
  }
  CHECK(refused);
}

void test_spline_reads_the_edge_beyond_it() {
  const std::vector<double> c = {1, 2, 3, 4, 5, 6};   // 2 x 3
  const Image image{c.data(), 2, 3};
  // far beyond every edge, and at huge or tiny coordinates, the value is the nearest edge coefficient's
  CHECK_NEAR(sample_spline(image, -1e300, -1e300), 1.0, 1e-12);
  CHECK_NEAR(sample_spline(image, 1e300, 1e300), 6.0, 1e-12);
  CHECK_NEAR(sample_spline(image, -50.0, 1e9), 3.0, 1e-12);
  // a constant is reproduced everywhere (the weights sum to one)
  const std::vector<double> ones(12, 2.5);
  const Image flat{ones.data(), 3, 4};
  CHECK_NEAR(sample_spline(flat, 1.37, 2.91), 2.5, 1e-12);
  const std::vector<double> single = {4.0};
  CHECK_NEAR(sample_spline(Image{single.data(), 1, 1}, 0.3, -0.7), 4.0, 1e-12);
}

void test_a_shift_is_found() {
  const Scene s = scene(96, 96, 1.3, -0.6);
  Settings settings{16, 64, 20, 1e-4, 1e-5};
  std::vector<bool> dummy;
  const std::vector<char> used(16 * 16, 1);
  const WindowResult r = match_window(s.pair(), settings, 48, 48, reinterpret_cast<const bool*>(used.data()));
  CHECK(r.status == Status::matched);
  // the texture is not a B-spline of these coefficients exactly, so the match is close, not exact
  CHECK_NEAR(r.warp[2], 1.3, 0.05);
  CHECK_NEAR(r.warp[5], -0.6, 0.05);
  CHECK_NEAR(r.start[0], 1.3, 0.5);
  CHECK(r.iterations >= 1 && r.iterations <= 20);
}

void test_border_tiny_and_nan_inputs_are_rejected_not_read() {
  Scene s = scene(40, 40, 0.4, 0.2);
  Settings settings{16, 64, 20, 1e-4, 1e-5};
  const std::vector<char> mask(16 * 16, 1);
  const bool* used = reinterpret_cast<const bool*>(mask.data());
  // windows that do not fit, at every side and far away, and one whose search area leaves the image (allowed: the
  // spline reads the edge beyond it)
  const std::vector<std::int64_t> centres = {7, 20, 20, 7, 33, 20, 20, 33, -1000000, 5, 5, 1000000, 8, 8, 20, 20};
  std::vector<char> masks(8 * 16 * 16, 1);
  const auto results = match_windows(s.pair(), settings, centres.data(), 8,
                                     reinterpret_cast<const bool*>(masks.data()), 3);
  for (int k = 0; k < 6; ++k) CHECK(results[k].status == Status::outside);
  CHECK(results[6].status == Status::matched);
  CHECK(results[7].status == Status::matched);
  // a NaN pixel in the template, then in the search area only
  s.reference[20 * 40 + 20] = std::numeric_limits<double>::quiet_NaN();
  CHECK(match_window(s.pair(), settings, 20, 20, used).status == Status::not_finite);
  s.reference[20 * 40 + 20] = 1.0;
  s.deformed[2 * 40 + 2] = std::numeric_limits<double>::infinity();
  CHECK(match_window(s.pair(), settings, 20, 20, used).status == Status::not_finite);
  s.deformed[2 * 40 + 2] = 1.0;
  // a prior field holding a NaN
  std::vector<double> prior(2 * 40 * 40, 0.0);
  prior[40 * 40 + 21 * 40 + 19] = std::numeric_limits<double>::quiet_NaN();
  Pair with_prior = s.pair();
  with_prior.prior = prior.data();
  CHECK(match_window(with_prior, settings, 20, 20, used).status == Status::not_finite);
  // a flat template, and a window whose pixel set is empty
  const std::vector<double> flat(40 * 40, 3.0);
  Pair flat_pair = s.pair();
  flat_pair.reference = {flat.data(), 40, 40};
  CHECK(match_window(flat_pair, settings, 20, 20, used).status == Status::flat);
  const std::vector<char> none(16 * 16, 0);
  CHECK(match_window(s.pair(), settings, 20, 20, reinterpret_cast<const bool*>(none.data())).status ==
        Status::refinement_failed);
  // images smaller than a window, a one-pixel window, and settings that make no sense
  const Scene tiny = scene(3, 5, 0.0, 0.0);
  const std::vector<std::int64_t> one = {1, 2};
  CHECK(match_windows(tiny.pair(), settings, one.data(), 1, used, 1)[0].status == Status::outside);
  Settings single{1, 4, 20, 1e-4, 1e-5};
  const std::vector<char> one_pixel(1, 1);
  CHECK(match_windows(tiny.pair(), single, one.data(), 1, reinterpret_cast<const bool*>(one_pixel.data()), 1)[0]
            .status != Status::matched);
  bool refused = false;
  try {
    Settings bad{16, 8, 20, 1e-4, 1e-5};
    match_windows(s.pair(), bad, one.data(), 1, used, 1);
  } catch (const std::invalid_argument&) {
    refused = true;
  }
  CHECK(refused);
}

void test_threads_give_the_windows_of_one_thread() {
  const Scene s = scene(80, 120, 0.7, 0.35);
  Settings settings{16, 48, 20, 1e-4, 1e-5};
  std::vector<std::int64_t> centres;
  for (std::int64_t r = 8; r <= 72; r += 8)
    for (std::int64_t c = 8; c <= 112; c += 8) centres.insert(centres.end(), {r, c});
  const std::size_t count = centres.size() / 2;
  std::vector<char> masks(count * 256, 1);
  const auto* used = reinterpret_cast<const bool*>(masks.data());
  const auto one = match_windows(s.pair(), settings, centres.data(), count, used, 1);
  const auto many = match_windows(s.pair(), settings, centres.data(), count, used, 4);
  bool same = true;
  for (std::size_t k = 0; k < count; ++k)
    same = same && one[k].status == many[k].status && one[k].warp == many[k].warp && one[k].start == many[k].start;
  CHECK(same);
}

}  // namespace

int main() {
  test_fft_round_trip_and_correlation();
  test_spline_reads_the_edge_beyond_it();
  test_a_shift_is_found();
  test_border_tiny_and_nan_inputs_are_rejected_not_read();
  test_threads_give_the_windows_of_one_thread();
  return calfit::testing::tally().finish();
}
