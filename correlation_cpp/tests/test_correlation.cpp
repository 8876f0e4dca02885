// The DIC windows' hot loops (correlation_cpp/src/windows.hpp) on inputs whose answer is known, and on inputs that
// must be refused or rejected rather than read out of bounds: tiny images, windows at and beyond the border, NaN.
// orchestrator's tests/measure/test_compiled_windows.py holds the loops to the Python reference on the phantom.
#include <algorithm>
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
  std::vector<double> prior = {};   // (2, rows, cols) px, or empty: none
  Pair pair() const {
    Pair p;
    p.reference = {reference.data(), rows, cols};
    p.spline = {deformed.data(), rows, cols};
    p.grad_rows = {grad_rows.data(), rows, cols};
    p.grad_cols = {grad_cols.data(), rows, cols};
    p.to_deformed = {1, 0, 0, 0, 1, 0};
    p.prior = prior.empty() ? nullptr : prior.data();
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

// An image that is exactly a cubic B-spline: random coefficients, the reference their spline at the pixels, the
// deformed image's coefficients the same moved by whole pixels, so I1(x) = I0(x - shift) holds between the pixels too
// and Gauss-Newton must find the shift to its tolerance. A constant prior field takes the start off the integer grid.
Scene spline_scene(std::ptrdiff_t n, std::ptrdiff_t shift_col, std::ptrdiff_t shift_row, double prior_col,
                   double prior_row) {
  Scene s{n, n, {}, {}, {}, {}};
  std::vector<double> coefficients;
  std::mt19937 random(11);
  std::normal_distribution<double> grain(100.0, 20.0);
  for (std::ptrdiff_t k = 0; k < n * n; ++k) coefficients.push_back(grain(random));
  const Image c{coefficients.data(), n, n};
  for (std::ptrdiff_t r = 0; r < n; ++r)
    for (std::ptrdiff_t q = 0; q < n; ++q) {
      const double y = static_cast<double>(r), x = static_cast<double>(q);
      s.reference.push_back(sample_spline(c, y, x));
      const std::ptrdiff_t from_r = std::clamp(r - shift_row, std::ptrdiff_t{0}, n - 1);
      const std::ptrdiff_t from_c = std::clamp(q - shift_col, std::ptrdiff_t{0}, n - 1);
      s.deformed.push_back(coefficients[from_r * n + from_c]);
      s.grad_rows.push_back((sample_spline(c, y + 1e-4, x) - sample_spline(c, y - 1e-4, x)) / 2e-4);
      s.grad_cols.push_back((sample_spline(c, y, x + 1e-4) - sample_spline(c, y, x - 1e-4)) / 2e-4);
    }
  s.prior.assign(n * n, prior_col);
  s.prior.resize(2 * n * n, prior_row);
  return s;
}

// Both shape functions find the shift less the prior exactly; the quadratic one finds no bend, its linear part the
// identity. Rows x', y' of the map over (dx, dy, 1) affine, over (dx^2, dx dy, dy^2, dx, dy, 1) quadratic.
void test_each_shape_finds_the_shift_of_a_spline_image_exactly() {
  const Scene s = spline_scene(96, 2, -1, 0.3, -0.45);
  const std::vector<char> used(24 * 24, 1);
  for (int order : {1, 2}) {
    Settings settings{24, 64, 20, 1e-8, 1e-9, order};
    const WindowResult r = match_window(s.pair(), settings, 48, 48, reinterpret_cast<const bool*>(used.data()));
    CHECK(r.status == Status::matched);
    const int k = order == 1 ? 3 : 6;
    CHECK_NEAR(r.warp[k - 1], 2.0 - 0.3, 1e-6);
    CHECK_NEAR(r.warp[2 * k - 1], -1.0 + 0.45, 1e-6);
    CHECK_NEAR(r.warp[k - 3], 1.0, 1e-6);
    CHECK_NEAR(r.warp[2 * k - 2], 1.0, 1e-6);
    CHECK_NEAR(r.warp[k - 2], 0.0, 1e-6);
    CHECK_NEAR(r.warp[2 * k - 3], 0.0, 1e-6);
    if (order == 2)
      for (int j : {0, 1, 2, 6, 7, 8}) CHECK_NEAR(r.warp[j], 0.0, 1e-7);
    CHECK(r.iterations >= 2);   // the prior's fraction of a pixel took Gauss-Newton off the start
  }
  bool refused = false;
  try {
    Settings cubic{16, 64, 20, 1e-4, 1e-5, 3};
    const std::vector<std::int64_t> one = {48, 48};
    match_windows(s.pair(), cubic, one.data(), 1, reinterpret_cast<const bool*>(used.data()), 1);
  } catch (const std::invalid_argument&) {
    refused = true;
  }
  CHECK(refused);
}

// shape_order: the window's shape function (1 affine, 2 quadratic), through the same rejections
void test_border_tiny_and_nan_inputs_are_rejected_not_read(int shape_order) {
  Scene s = scene(40, 40, 0.4, 0.2);
  Settings settings{16, 64, 20, 1e-4, 1e-5, shape_order};
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
  Settings single{1, 4, 20, 1e-4, 1e-5, shape_order};
  const std::vector<char> one_pixel(1, 1);
  CHECK(match_windows(tiny.pair(), single, one.data(), 1, reinterpret_cast<const bool*>(one_pixel.data()), 1)[0]
            .status != Status::matched);
  bool refused = false;
  try {
    Settings bad{16, 8, 20, 1e-4, 1e-5, shape_order};
    match_windows(s.pair(), bad, one.data(), 1, used, 1);
  } catch (const std::invalid_argument&) {
    refused = true;
  }
  CHECK(refused);
}

void test_threads_give_the_windows_of_one_thread(int shape_order) {
  const Scene s = scene(80, 120, 0.7, 0.35);
  Settings settings{16, 48, 20, 1e-4, 1e-5, shape_order};
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

// The error terms (error_model.hpp) on the exactly shifted spline image, without a prefilter and with the noise
// share rho = 1 everywhere: the noise's covariance is s_e^2 H_s^-1 H H_s^-1, so with no noise in the reference
// (H_s = H) it is s_e^2 H^-1 and scales as the deformed image's noise squared; the residual of an exact match is
// nothing; noise above the texture leaves the window untextured; and the fallback rules read the start's ZNCC.
void test_the_error_terms_of_an_exact_match(int shape_order) {
  const Scene s = spline_scene(96, 2, -1, 0.3, -0.45);
  const std::size_t cells = 96 * 96;
  const std::vector<double> ones(cells, 1.0), edges(cells, 4.0);
  ErrorMaps maps;
  maps.noise_q = maps.rho_raw = {ones.data(), 96, 96};
  maps.edge_q = maps.edge_raw = {edges.data(), 96, 96};
  Settings settings{24, 64, 20, 1e-10, 1e-10, shape_order};
  const std::vector<char> mask(24 * 24, 1);
  const bool* used = reinterpret_cast<const bool*>(mask.data());
  auto terms = [&](double sigma_reference, double sigma_deformed, double max_refinement) {
    maps.noise_sigma = {sigma_reference, sigma_deformed};
    maps.max_refinement_px = max_refinement;
    Pair pair = s.pair();
    pair.errors = &maps;
    const WindowResult r = match_window(pair, settings, 48, 48, used);
    CHECK(r.status == Status::matched);
    return r.error;
  };
  const WindowError one = terms(0.0, 1.0, 3.0), two = terms(0.0, 2.0, 3.0);
  CHECK(one.textured && !one.at_start);
  CHECK_NEAR(one.confidence, 1.0, 1e-9);   // no prefilter: the raw ZNCC is the matched one
  CHECK_NEAR(one.zncc, 1.0, 1e-9);
  CHECK(one.covariance[0] > 0.0 && one.covariance[3] > 0.0);
  CHECK_NEAR(one.covariance[1], one.covariance[2], 1e-12 * one.covariance[0]);
  CHECK(one.covariance[0] * one.covariance[3] > one.covariance[1] * one.covariance[1]);
  for (int j = 0; j < 4; ++j) CHECK_NEAR(two.covariance[j], 4.0 * one.covariance[j], 1e-9 * one.covariance[0]);
  // the edges' part per unit s_edge^2: |grad I|^2 = 4 where rho = 1, so four times the noise's per unit s_e^2
  for (int j = 0; j < 4; ++j) CHECK_NEAR(one.edge_covariance[j], 4.0 * one.covariance[j] / one.variance,
                                          1e-9 * one.edge_covariance[0]);
  CHECK(one.edge_sums[0] == 24.0 * 24.0);
  CHECK(one.edge_sums[3] < 1e-6 * one.edge_sums[0]);   // y: the residual's squares of an exact match
  CHECK(!terms(1e4, 1.0, 3.0).textured);                // reference noise far above the texture
  const WindowError fallback = terms(0.0, 1.0, 0.0);   // no refinement allowed: measured at the start
  CHECK(fallback.at_start && fallback.start_confidence > 0.9 && fallback.start_confidence < 1.0);
}

}  // namespace

int main() {
  test_fft_round_trip_and_correlation();
  test_spline_reads_the_edge_beyond_it();
  test_a_shift_is_found();
  test_each_shape_finds_the_shift_of_a_spline_image_exactly();
  for (int shape_order : {1, 2}) {
    test_border_tiny_and_nan_inputs_are_rejected_not_read(shape_order);
    test_threads_give_the_windows_of_one_thread(shape_order);
    test_the_error_terms_of_an_exact_match(shape_order);
  }
  return calfit::testing::tally().finish();
}
