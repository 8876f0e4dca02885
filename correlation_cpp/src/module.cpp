// orchestrator._correlation: the DIC windows' hot loops (windows.hpp) for orchestrator/measure/dic.py. The arrays
// are checked here, each misfit refused with one sentence (ValueError), so that the loops read only what exists.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>

#include <cmath>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>

#include "windows.hpp"

namespace nb = nanobind;
using namespace calfit::correlation;

namespace {

using Grid = nb::ndarray<const double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using Field = nb::ndarray<const double, nb::ndim<3>, nb::c_contig, nb::device::cpu>;
using Centres = nb::ndarray<const std::int64_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using Masks = nb::ndarray<const bool, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using Line = nb::ndarray<const double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

template <typename T>
nb::ndarray<nb::numpy, T> owned(T* data, std::initializer_list<std::size_t> shape) {
  nb::capsule owner(data, [](void* p) noexcept { delete[] static_cast<T*>(p); });
  return nb::ndarray<nb::numpy, T>(data, shape, owner);
}

std::string shape_of(std::size_t rows, std::size_t cols) {
  return "(" + std::to_string(rows) + ", " + std::to_string(cols) + ")";
}

Image image_of(const Grid& grid) {
  return {grid.data(), static_cast<std::ptrdiff_t>(grid.shape(0)), static_cast<std::ptrdiff_t>(grid.shape(1))};
}

// The error model's maps (error_model.hpp), checked against the reference's shape: every map or none of them.
std::optional<ErrorMaps> error_maps(std::size_t rows, std::size_t cols, const std::optional<Grid>& raw_reference,
                                    const std::optional<Grid>& raw_spline, const std::optional<Grid>& noise_q,
                                    const std::optional<Grid>& edge_q, const std::optional<Grid>& rho_raw,
                                    const std::optional<Grid>& edge_raw, const std::optional<Line>& kernel,
                                    double noise_gain, double derivative_noise_gain, double noise_sigma_reference,
                                    double noise_sigma_deformed, double max_refinement_px, double zncc_slack) {
  const bool any = noise_q || edge_q || rho_raw || edge_raw || kernel || raw_reference || raw_spline;
  if (!any) return std::nullopt;
  if (!(noise_q && edge_q && rho_raw && edge_raw && kernel))
    throw std::invalid_argument("the error model needs noise_q, edge_q, rho_raw, edge_raw and kernel together");
  if (raw_reference.has_value() != raw_spline.has_value())
    throw std::invalid_argument("the raw images come as a pair: raw_reference and raw_spline, or neither");
  const std::size_t taps = kernel->shape(0);
  if (taps % 2 == 0) throw std::invalid_argument("the prefilter's kernel has an odd number of taps, not " +
                                                  std::to_string(taps));
  const std::size_t reach = (taps - 1) / 2;
  for (const auto* grid : {&noise_q, &edge_q, &raw_reference, &raw_spline})
    if (*grid && ((*grid)->shape(0) != rows || (*grid)->shape(1) != cols))
      throw std::invalid_argument("the raw images, noise_q and edge_q must have the reference's shape " +
                                  shape_of(rows, cols) + ", not " + shape_of((*grid)->shape(0), (*grid)->shape(1)));
  for (const auto* grid : {&rho_raw, &edge_raw})
    if ((*grid)->shape(0) != rows + 2 * reach || (*grid)->shape(1) != cols + 2 * reach)
      throw std::invalid_argument("rho_raw and edge_raw are the reference's shape padded by the kernel's radius: " +
                                  shape_of(rows + 2 * reach, cols + 2 * reach) + ", not " +
                                  shape_of((*grid)->shape(0), (*grid)->shape(1)));
  for (double v : {noise_gain, derivative_noise_gain, noise_sigma_reference, noise_sigma_deformed, max_refinement_px,
                   zncc_slack})
    if (!(v >= 0.0) || !std::isfinite(v))
      throw std::invalid_argument("the noise gains and sigmas, the largest refinement and the ZNCC's slack are finite "
                                  "and not negative");
  if (!(noise_gain > 0.0)) throw std::invalid_argument("the prefilter's noise gain is positive");
  ErrorMaps maps;
  if (raw_reference) {
    maps.raw_reference = image_of(*raw_reference);
    maps.raw_spline = image_of(*raw_spline);
  }
  maps.noise_q = image_of(*noise_q);
  maps.edge_q = image_of(*edge_q);
  maps.rho_raw = image_of(*rho_raw);
  maps.edge_raw = image_of(*edge_raw);
  maps.kernel.assign(kernel->data(), kernel->data() + taps);
  maps.noise_gain = noise_gain;
  maps.derivative_noise_gain = derivative_noise_gain;
  maps.noise_sigma = {noise_sigma_reference, noise_sigma_deformed};
  maps.max_refinement_px = max_refinement_px;
  maps.zncc_slack = zncc_slack;
  return maps;
}

// Each window's error terms as arrays (the keys dic._compiled_search reads)
void put_errors(nb::dict& out, const std::vector<WindowResult>& results) {
  const std::size_t count = results.size();
  auto* flags = new bool[3 * count];
  auto* scores = new double[4 * count];
  auto* covariances = new double[8 * count];
  auto* sums = new double[5 * count];
  for (std::size_t k = 0; k < count; ++k) {
    const WindowError& e = results[k].error;
    flags[3 * k] = e.conditioned;
    flags[3 * k + 1] = e.textured;
    flags[3 * k + 2] = e.at_start;
    const double values[4] = {e.zncc, e.confidence, e.start_confidence, e.variance};
    std::copy(values, values + 4, scores + 4 * k);
    std::copy(e.covariance.begin(), e.covariance.end(), covariances + 8 * k);
    std::copy(e.edge_covariance.begin(), e.edge_covariance.end(), covariances + 8 * k + 4);
    std::copy(e.edge_sums.begin(), e.edge_sums.end(), sums + 5 * k);
  }
  out["flags"] = owned(flags, {count, 3});
  out["scores"] = owned(scores, {count, 4});
  out["covariances"] = owned(covariances, {count, 2, 2, 2});
  out["edge_sums"] = owned(sums, {count, 5});
}

nb::dict match_windows_py(Grid reference, Grid spline, Grid grad_rows, Grid grad_cols, Grid to_deformed,
                          std::optional<Field> prior, Centres centres, Masks used, int window_px, int search_px,
                          int iterations, double tolerance_px, double tolerance_gradient, int threads,
                          int shape_order, std::optional<Grid> raw_reference, std::optional<Grid> raw_spline,
                          std::optional<Grid> noise_q, std::optional<Grid> edge_q, std::optional<Grid> rho_raw,
                          std::optional<Grid> edge_raw, std::optional<Line> kernel, double noise_gain,
                          double derivative_noise_gain, double noise_sigma_reference, double noise_sigma_deformed,
                          double max_refinement_px, double zncc_slack) {
  const std::size_t rows = reference.shape(0), cols = reference.shape(1);
  if (rows == 0 || cols == 0) throw std::invalid_argument("the reference image is empty");
  for (const Grid* grid : {&spline, &grad_rows, &grad_cols})
    if (grid->shape(0) != rows || grid->shape(1) != cols)
      throw std::invalid_argument("the spline coefficients and the gradients must have the reference's shape " +
                                  shape_of(rows, cols) + ", not " + shape_of(grid->shape(0), grid->shape(1)));
  if (to_deformed.shape(0) != 3 || to_deformed.shape(1) != 3)
    throw std::invalid_argument("the prior motion is a 3x3 matrix on (column, row, 1)");
  if (prior && (prior->shape(0) != 2 || prior->shape(1) != rows || prior->shape(2) != cols))
    throw std::invalid_argument("the prior field must be (2, " + std::to_string(rows) + ", " + std::to_string(cols) +
                                ") pixels");
  if (window_px < 1 || search_px < window_px)
    throw std::invalid_argument("a window of at least one pixel and a search area at least as large: window_px " +
                                std::to_string(window_px) + ", search_px " + std::to_string(search_px));
  if (iterations < 0 || !(tolerance_px >= 0.0) || !(tolerance_gradient >= 0.0))
    throw std::invalid_argument("Gauss-Newton's iterations and tolerances cannot be negative");
  if (threads < 1) throw std::invalid_argument("at least one thread matches the windows");
  if (shape_order != 1 && shape_order != 2)
    throw std::invalid_argument("the window's shape function is of order 1 (affine) or 2 (quadratic), not " +
                                std::to_string(shape_order));
  const std::size_t count = centres.shape(0);
  const std::size_t square = static_cast<std::size_t>(window_px) * static_cast<std::size_t>(window_px);
  if (centres.shape(1) != 2) throw std::invalid_argument("the window centres are (N, 2) (row, column) pixels");
  if (used.shape(0) != count || used.shape(1) != square)
    throw std::invalid_argument("one pixel set of " + std::to_string(square) + " per window: " +
                                shape_of(count, square) + ", not " + shape_of(used.shape(0), used.shape(1)));

  Pair pair;
  pair.reference = {reference.data(), static_cast<std::ptrdiff_t>(rows), static_cast<std::ptrdiff_t>(cols)};
  pair.spline = {spline.data(), pair.reference.rows, pair.reference.cols};
  pair.grad_rows = {grad_rows.data(), pair.reference.rows, pair.reference.cols};
  pair.grad_cols = {grad_cols.data(), pair.reference.rows, pair.reference.cols};
  for (int k = 0; k < 6; ++k) pair.to_deformed[k] = to_deformed.data()[k];
  pair.prior = prior ? prior->data() : nullptr;
  const std::optional<ErrorMaps> maps =
      error_maps(rows, cols, raw_reference, raw_spline, noise_q, edge_q, rho_raw, edge_raw, kernel, noise_gain,
                 derivative_noise_gain, noise_sigma_reference, noise_sigma_deformed, max_refinement_px, zncc_slack);
  pair.errors = maps ? &*maps : nullptr;
  Settings settings{window_px, search_px, iterations, tolerance_px, tolerance_gradient, shape_order};

  std::vector<WindowResult> results;
  {
    nb::gil_scoped_release free_python;   // the arrays stay alive: their Python objects are this call's arguments
    results = match_windows(pair, settings, centres.data(), count, used.data(), threads);
  }
  auto* status = new std::int8_t[count];
  auto* start = new double[2 * count];
  auto* peak = new double[count];
  const std::size_t terms = shape_order == 2 ? 6 : 3;   // per row of the map (windows.hpp)
  auto* warp = new double[2 * terms * count];
  auto* steps = new std::int32_t[count];
  for (std::size_t k = 0; k < count; ++k) {
    status[k] = static_cast<std::int8_t>(results[k].status);
    start[2 * k] = results[k].start[0];
    start[2 * k + 1] = results[k].start[1];
    peak[k] = results[k].peak_score;
    for (std::size_t j = 0; j < 2 * terms; ++j) warp[2 * terms * k + j] = results[k].warp[j];
    steps[k] = results[k].iterations;
  }
  nb::dict out;
  out["status"] = owned(status, {count});
  out["start"] = owned(start, {count, 2});
  out["peak_score"] = owned(peak, {count});
  out["warp"] = owned(warp, {count, 2, terms});
  out["iterations"] = owned(steps, {count});
  if (maps) put_errors(out, results);
  return out;
}

nb::ndarray<nb::numpy, double> sample_py(Grid coefficients, nb::ndarray<const double, nb::ndim<1>, nb::c_contig,
                                         nb::device::cpu> rows, nb::ndarray<const double, nb::ndim<1>, nb::c_contig,
                                         nb::device::cpu> cols) {
  if (coefficients.shape(0) == 0 || coefficients.shape(1) == 0)
    throw std::invalid_argument("the spline coefficients are empty");
  if (rows.shape(0) != cols.shape(0)) throw std::invalid_argument("as many rows as columns to sample at");
  const Image image{coefficients.data(), static_cast<std::ptrdiff_t>(coefficients.shape(0)),
                    static_cast<std::ptrdiff_t>(coefficients.shape(1))};
  const std::size_t count = rows.shape(0);
  auto* values = new double[count];
  for (std::size_t k = 0; k < count; ++k) {
    const double r = rows.data()[k], c = cols.data()[k];
    values[k] = std::isfinite(r) && std::isfinite(c) ? sample_spline(image, r, c) : std::nan("");
  }
  return owned(values, {count});
}

nb::tuple spline_gradient_py(Grid coefficients, double step) {
  if (coefficients.shape(0) == 0 || coefficients.shape(1) == 0)
    throw std::invalid_argument("the spline coefficients are empty");
  if (!(step > 0.0) || !std::isfinite(step)) throw std::invalid_argument("the difference step must be positive");
  const auto rows = static_cast<std::ptrdiff_t>(coefficients.shape(0));
  const auto cols = static_cast<std::ptrdiff_t>(coefficients.shape(1));
  const Image image{coefficients.data(), rows, cols};
  auto* along_rows = new double[rows * cols];
  auto* along_cols = new double[rows * cols];
  {
    nb::gil_scoped_release free_python;
    spline_gradient(image, step, along_rows, along_cols);
  }
  return nb::make_tuple(owned(along_rows, {coefficients.shape(0), coefficients.shape(1)}),
                        owned(along_cols, {coefficients.shape(0), coefficients.shape(1)}));
}

}  // namespace

NB_MODULE(_correlation, m) {
  m.doc() = "calfit's DIC windows: the ZNCC integer search, the IC-GN iterations and each window's error terms "
            "(orchestrator/measure/dic.py)";
  m.attr("MATCHED") = static_cast<int>(Status::matched);
  m.attr("OUTSIDE") = static_cast<int>(Status::outside);
  m.attr("FLAT") = static_cast<int>(Status::flat);
  m.attr("REFINEMENT_FAILED") = static_cast<int>(Status::refinement_failed);
  m.attr("NOT_FINITE") = static_cast<int>(Status::not_finite);
  m.def("match_windows", &match_windows_py, nb::arg("reference"), nb::arg("spline"), nb::arg("grad_rows"),
        nb::arg("grad_cols"), nb::arg("to_deformed"), nb::arg("prior").none(), nb::arg("centres"), nb::arg("used"),
        nb::arg("window_px"), nb::arg("search_px"), nb::arg("iterations"), nb::arg("tolerance_px"),
        nb::arg("tolerance_gradient"), nb::arg("threads") = 1, nb::arg("shape_order") = 1,
        nb::arg("raw_reference").none() = nb::none(), nb::arg("raw_spline").none() = nb::none(),
        nb::arg("noise_q").none() = nb::none(), nb::arg("edge_q").none() = nb::none(),
        nb::arg("rho_raw").none() = nb::none(), nb::arg("edge_raw").none() = nb::none(),
        nb::arg("kernel").none() = nb::none(), nb::arg("noise_gain") = 1.0, nb::arg("derivative_noise_gain") = 1.0,
        nb::arg("noise_sigma_reference") = 0.0, nb::arg("noise_sigma_deformed") = 0.0,
        nb::arg("max_refinement_px") = 3.0, nb::arg("zncc_slack") = 0.02,
        "Per window: status, start (d_col, d_row), peak_score, warp (2 x 3 affine, 2 x 6 quadratic: the map's rows "
        "over the monomials) and iterations (windows.hpp); given the error model's maps (error_model.hpp), also "
        "flags (conditioned, textured, at_start), scores (zncc, confidence, start_confidence, variance), covariances (noise, "
        "edges; 2 x 2 px^2 each) and edge_sums (count, z, zz, y, yz).");
  m.def("spline_gradient", &spline_gradient_py, nb::arg("coefficients"), nb::arg("step"),
        "(d/drow, d/dcolumn) at every pixel of the cubic B-spline of the coefficients, by a central difference of "
        "`step` pixels (dic.spline_derivatives).");
  m.def("sample_spline", &sample_py, nb::arg("coefficients"), nb::arg("rows"), nb::arg("cols"),
        "The cubic B-spline of the coefficients at the points, as map_coordinates(order=3, prefilter=False, "
        "mode='nearest') (NaN at a non-finite point).");
}
