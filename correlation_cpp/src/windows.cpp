#include "windows.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <complex>
#include <exception>
#include <limits>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>

#include "fft.hpp"
#include "window_system.hpp"

namespace calfit::correlation {
namespace {

using Complex = std::complex<double>;

// The prior field (d_col, d_row) at an integer pixel, held constant beyond the image (dic._prior_at).
inline void prior_at(const Pair& pair, std::ptrdiff_t r, std::ptrdiff_t c, double& d_col, double& d_row) {
  if (pair.prior == nullptr) {
    d_col = d_row = 0.0;
    return;
  }
  const std::ptrdiff_t rows = pair.reference.rows, cols = pair.reference.cols;
  r = std::clamp(r, std::ptrdiff_t{0}, rows - 1);
  c = std::clamp(c, std::ptrdiff_t{0}, cols - 1);
  d_col = pair.prior[r * cols + c];
  d_row = pair.prior[rows * cols + r * cols + c];
}

// Sub-pixel offset of the maximum of a parabola through a peak and its two neighbours (dic._parabola_offset).
double parabola_offset(double left, double centre, double right) {
  const double curvature = left - 2.0 * centre + right;
  return curvature >= 0.0 ? 0.0 : std::clamp(0.5 * (left - right) / curvature, -0.5, 0.5);
}

// What one thread reuses from window to window: the FFT plan of the search's size and its grids.
struct Workspace {
  explicit Workspace(std::size_t n) : fft(n), spectrum(n * n), product(n * n) {}
  Fft fft;
  std::vector<Complex> spectrum, product;
};

std::vector<double> zncc_map_with(Workspace& ws, const std::vector<double>& patch, std::ptrdiff_t p,
                                  const std::vector<double>& tmpl, std::ptrdiff_t w) {
  const std::ptrdiff_t m = p - w + 1;
  const auto n = static_cast<std::ptrdiff_t>(ws.fft.size());
  const double count = static_cast<double>(w * w);
  // The patch and the template mean-free: the ZNCC does not change, and the window sums below lose less to
  // cancellation than skimage's running sums of the raw grey levels.
  double patch_mean = 0.0, tmpl_mean = 0.0;
  for (double v : patch) patch_mean += v;
  for (double v : tmpl) tmpl_mean += v;
  patch_mean /= static_cast<double>(p * p);
  tmpl_mean /= count;
  double tmpl_ssd = 0.0;
  for (double v : tmpl) tmpl_ssd += (v - tmpl_mean) * (v - tmpl_mean);

  // Two real grids in one complex transform (patch + i template), split by the spectrum's conjugate symmetry; the
  // circular correlation of size n >= p does not wrap at the shifts kept, whose template stays inside the patch.
  std::fill(ws.spectrum.begin(), ws.spectrum.end(), Complex{});
  for (std::ptrdiff_t r = 0; r < p; ++r)
    for (std::ptrdiff_t c = 0; c < p; ++c) ws.spectrum[r * n + c] = {patch[r * p + c] - patch_mean, 0.0};
  for (std::ptrdiff_t r = 0; r < w; ++r)
    for (std::ptrdiff_t c = 0; c < w; ++c) ws.spectrum[r * n + c].imag(tmpl[r * w + c] - tmpl_mean);
  ws.fft.transform_2d(ws.spectrum, false);
  // (the spectrum is transposed, `Fft::transform_2d`, and so is the mirror of a frequency: the formula is the same)
  for (std::ptrdiff_t r = 0; r < n; ++r) {
    for (std::ptrdiff_t c = 0; c < n; ++c) {
      const Complex z = ws.spectrum[r * n + c], mirrored = std::conj(ws.spectrum[((n - r) % n) * n + (n - c) % n]);
      // patch's spectrum P = (z + mirrored) / 2, template's T = (z - mirrored) / 2i; P conj(T) in real arithmetic
      const double pr = 0.5 * (z.real() + mirrored.real()), pi = 0.5 * (z.imag() + mirrored.imag());
      const double tr = 0.5 * (z.imag() - mirrored.imag()), ti = -0.5 * (z.real() - mirrored.real());
      ws.product[r * n + c] = {pr * tr + pi * ti, pi * tr - pr * ti};
    }
  }
  ws.fft.transform_2d(ws.product, true);
  const double scale = 1.0 / static_cast<double>(n * n);

  // the windows' sums of the patch and its square from summed-area tables
  std::vector<double> sum((p + 1) * (p + 1), 0.0), sum2((p + 1) * (p + 1), 0.0);
  for (std::ptrdiff_t r = 0; r < p; ++r) {
    for (std::ptrdiff_t c = 0; c < p; ++c) {
      const double v = patch[r * p + c] - patch_mean;
      const std::ptrdiff_t at = (r + 1) * (p + 1) + c + 1;
      sum[at] = v + sum[at - 1] + sum[at - (p + 1)] - sum[at - (p + 1) - 1];
      sum2[at] = v * v + sum2[at - 1] + sum2[at - (p + 1)] - sum2[at - (p + 1) - 1];
    }
  }
  auto box = [&](const std::vector<double>& table, std::ptrdiff_t r, std::ptrdiff_t c) {
    const std::ptrdiff_t s = p + 1;
    return table[(r + w) * s + c + w] - table[r * s + c + w] - table[(r + w) * s + c] + table[r * s + c];
  };
  std::vector<double> score(m * m, 0.0);
  for (std::ptrdiff_t r = 0; r < m; ++r) {
    for (std::ptrdiff_t c = 0; c < m; ++c) {
      const double s = box(sum, r, c);
      const double variance = std::max(box(sum2, r, c) - s * s / count, 0.0);
      const double denominator = std::sqrt(variance * tmpl_ssd);
      // skimage's guard against a flat patch: below float64's epsilon the score is 0
      if (denominator > std::numeric_limits<double>::epsilon())
        score[r * m + c] = ws.product[r * n + c].real() * scale / denominator;
    }
  }
  return score;
}

// LU factors with partial pivoting of a small dense matrix (IC-GN's 6x6 or 12x12 Gauss-Newton matrix, kept for all
// its iterations; a quadratic map's 6x6 matrix, inverted once per step).
class Lu {
 public:
  bool factor(const std::vector<double>& matrix, int n) {
    n_ = n;
    a_ = matrix;
    pivot_.assign(n, 0);
    for (int k = 0; k < n; ++k) {
      int best = k;
      for (int i = k + 1; i < n; ++i)
        if (std::abs(a_[i * n + k]) > std::abs(a_[best * n + k])) best = i;
      pivot_[k] = best;
      if (!(std::abs(a_[best * n + k]) > 0.0) || !std::isfinite(a_[best * n + k])) return false;
      if (best != k)
        for (int j = 0; j < n; ++j) std::swap(a_[k * n + j], a_[best * n + j]);
      for (int i = k + 1; i < n; ++i) {
        a_[i * n + k] /= a_[k * n + k];
        for (int j = k + 1; j < n; ++j) a_[i * n + j] -= a_[i * n + k] * a_[k * n + j];
      }
    }
    return true;
  }
  std::vector<double> solve(std::vector<double> b) const {
    const int n = n_;
    // the rows were swapped whole while factoring (L too), so all the swaps come before the substitution
    for (int k = 0; k < n; ++k) std::swap(b[k], b[pivot_[k]]);
    for (int k = 0; k < n; ++k)
      for (int i = k + 1; i < n; ++i) b[i] -= a_[i * n + k] * b[k];
    for (int k = n - 1; k >= 0; --k) {
      for (int j = k + 1; j < n; ++j) b[k] -= a_[k * n + j] * b[j];
      b[k] /= a_[k * n + k];
    }
    return b;
  }

 private:
  int n_ = 0;
  std::vector<double> a_;
  std::vector<int> pivot_;
};

// The window's shape function (orchestrator/measure/shape.py): the basis of each displacement component and the
// monomials its map's matrix acts on, both at an offset (dx, dy) from the window centre.
struct ShapeFunction {
  int terms = 3;   // 3 affine, 6 quadratic
  void basis(double dx, double dy, double* out) const {
    out[0] = 1.0;
    out[1] = dx;
    out[2] = dy;
    if (terms == 6) {
      out[3] = 0.5 * dx * dx;
      out[4] = dx * dy;
      out[5] = 0.5 * dy * dy;
    }
  }
  void monomials(double dx, double dy, double* out) const {
    if (terms == 3) {
      out[0] = dx;
      out[1] = dy;
      out[2] = 1.0;
      return;
    }
    const double values[6] = {dx * dx, dx * dy, dy * dy, dx, dy, 1.0};
    std::copy(values, values + 6, out);
  }
};

// The exponents of (dx, dy) of a quadratic map's monomials (shape.py), the affine ones last.
constexpr int kMonomialExponents[6][2] = {{2, 0}, {1, 1}, {0, 2}, {1, 0}, {0, 1}, {0, 0}};

int monomial_index(int a, int b) {
  for (int k = 0; k < 6; ++k)
    if (kMonomialExponents[k][0] == a && kMonomialExponents[k][1] == b) return k;
  return -1;
}

// shape.lift: the 6x6 matrix (row-major) taking the monomials to those of (x', y'), the map's rows x' and y' over
// the monomials, each product's terms above second order dropped (Gao et al., Opt. Lasers Eng. 65, 2015, eqs. 8-10).
std::vector<double> lift(const double* x, const double* y) {
  std::vector<double> out(36, 0.0);
  auto product = [&](const double* a, const double* b, double* row) {
    for (int i = 0; i < 6; ++i)
      for (int j = 0; j < 6; ++j) {
        const int da = kMonomialExponents[i][0] + kMonomialExponents[j][0];
        const int db = kMonomialExponents[i][1] + kMonomialExponents[j][1];
        if (da + db <= 2) row[monomial_index(da, db)] += a[i] * b[j];
      }
  };
  product(x, x, &out[0]);
  product(x, y, &out[6]);
  product(y, y, &out[12]);
  std::copy(x, x + 6, &out[18]);
  std::copy(y, y + 6, &out[24]);
  out[35] = 1.0;
  return out;
}

// warp <- warp o W(p)^-1 for an affine window, W(p) = [[1 + ux, uy, u], [vx, 1 + vy, v]] inverted in closed form;
// warp holds the rows x', y' over (dx, dy, 1). False where W(p) is singular.
bool compose_affine(std::array<double, 12>& warp, const std::vector<double>& p) {
  const double a00 = 1.0 + p[1], a01 = p[2], a10 = p[4], a11 = 1.0 + p[5];
  const double det = a00 * a11 - a01 * a10;
  if (!(std::abs(det) > 0.0) || !std::isfinite(det)) return false;
  const double i00 = a11 / det, i01 = -a01 / det, i10 = -a10 / det, i11 = a00 / det;
  const double t0 = -(i00 * p[0] + i01 * p[3]), t1 = -(i10 * p[0] + i11 * p[3]);
  const std::array<double, 12> old = warp;
  for (int r = 0; r < 2; ++r) {
    const double o0 = old[r * 3], o1 = old[r * 3 + 1], o2 = old[r * 3 + 2];
    warp[r * 3] = o0 * i00 + o1 * i10;
    warp[r * 3 + 1] = o0 * i01 + o1 * i11;
    warp[r * 3 + 2] = o0 * t0 + o1 * t1 + o2;
  }
  return true;
}

// The same for a quadratic window through the maps' 6x6 matrices (shape.py): warp's rows x', y' over the six
// monomials become those of lift(warp) lift(W(p))^-1.
bool compose_quadratic(std::array<double, 12>& warp, const std::vector<double>& p) {
  const double x[6] = {0.5 * p[3], p[4], 0.5 * p[5], 1.0 + p[1], p[2], p[0]};
  const double y[6] = {0.5 * p[9], p[10], 0.5 * p[11], p[7], 1.0 + p[8], p[6]};
  Lu step;
  if (!step.factor(lift(x, y), 6)) return false;
  const std::vector<double> current = lift(&warp[0], &warp[6]);
  // rows r of current times the inverse: solve inverse^T row^T, i.e. each new row q with M^T q = row; done as the
  // columns of M^-1, six solves, since the LU is of M
  std::vector<double> inverse(36);
  for (int j = 0; j < 6; ++j) {
    std::vector<double> unit(6, 0.0);
    unit[j] = 1.0;
    const std::vector<double> column = step.solve(unit);
    for (int i = 0; i < 6; ++i) inverse[i * 6 + j] = column[i];
  }
  for (int r = 0; r < 2; ++r)
    for (int j = 0; j < 6; ++j) {
      double value = 0.0;
      for (int k = 0; k < 6; ++k) value += current[(3 + r) * 6 + k] * inverse[k * 6 + j];
      warp[r * 6 + j] = value;
    }
  for (double v : warp)
    if (!std::isfinite(v)) return false;
  return true;
}

// The window's IC-GN system at the reference over its used pixels (dic._inverse_compositional, before its loop):
// matched when it holds, refinement_failed for no pixel or a flat template, not_finite for a NaN in its gradients
// or the prior there.
Status build_system(const Pair& pair, const Settings& s, std::ptrdiff_t r0, std::ptrdiff_t c0, const bool* used,
                    WindowSystem& system) {
  const std::ptrdiff_t w = s.window_px;
  const double half = (static_cast<double>(w) - 1.0) / 2.0;
  const ShapeFunction shape{s.shape_order == 2 ? 6 : 3};
  const int k = shape.terms, np = 2 * k;
  system.r0 = r0;
  system.c0 = c0;
  system.size = w;
  system.terms = k;
  std::vector<double> dx, dy, gx, gy;
  for (std::ptrdiff_t r = 0; r < w; ++r) {
    for (std::ptrdiff_t c = 0; c < w; ++c) {
      if (!used[r * w + c]) continue;
      system.pixels.push_back(r * w + c);
      system.f.push_back(pair.reference.at(r0 + r, c0 + c));
      dx.push_back(static_cast<double>(c) - half);
      dy.push_back(static_cast<double>(r) - half);
      gx.push_back(pair.grad_cols.at(r0 + r, c0 + c));
      gy.push_back(pair.grad_rows.at(r0 + r, c0 + c));
      double pc = 0.0, pr = 0.0;
      prior_at(pair, r0 + r, c0 + c, pc, pr);
      system.prior_col.push_back(pc);
      system.prior_row.push_back(pr);
    }
  }
  const std::size_t n = system.pixels.size();
  if (n == 0) return Status::refinement_failed;
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(gx[i]) || !std::isfinite(gy[i]) || !std::isfinite(system.prior_col[i]) ||
        !std::isfinite(system.prior_row[i]))
      return Status::not_finite;
  system.f_norm = normalise(system.f);
  const std::vector<double>& f = system.f;

  // the steepest-descent images with the mean and f^ projected out (dic.zero_normalised_steepest_descent) and each
  // pixel's monomials (shape.py), row-major (n, np) and (n, k)
  system.steepest.assign(n * np, 0.0);
  system.monomials.assign(n * k, 0.0);
  std::vector<double> mean(np, 0.0), along_f(np, 0.0);
  double basis[6];
  for (std::size_t i = 0; i < n; ++i) {
    shape.basis(dx[i], dy[i], basis);
    shape.monomials(dx[i], dy[i], &system.monomials[i * k]);
    double* row = &system.steepest[i * np];
    for (int j = 0; j < k; ++j) {
      row[j] = gx[i] * basis[j];
      row[k + j] = gy[i] * basis[j];
    }
    for (int j = 0; j < np; ++j) {
      mean[j] += row[j];
      along_f[j] += f[i] * row[j];
    }
  }
  for (double& m : mean) m /= static_cast<double>(n);
  system.hessian.assign(np * np, 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    double* row = &system.steepest[i * np];
    for (int j = 0; j < np; ++j) row[j] -= mean[j] + f[i] * along_f[j];
    for (int a = 0; a < np; ++a)
      for (int b = 0; b < np; ++b) system.hessian[a * np + b] += row[a] * row[b];
  }
  return system.f_norm == 0.0 ? Status::refinement_failed : Status::matched;
}

// IC-GN from `out.start` on the window's system (dic._inverse_compositional's loop); fills warp and iterations.
Status refine(const Pair& pair, const Settings& s, const WindowSystem& system, WindowResult& out) {
  const int k = system.terms, np = system.parameters();
  const std::size_t n = system.pixels.size();
  const double f_norm = system.f_norm;
  std::vector<double> steepest = system.steepest, hessian = system.hessian;
  for (double& h : hessian) h /= f_norm * f_norm;
  for (double& v : steepest) v /= f_norm;
  Lu lu;
  if (!lu.factor(hessian, np)) return Status::refinement_failed;

  // the map's rows x', y' over the monomials, a translation by the start (shape.WindowShape.translated)
  Warp warp = translation_warp(k, out.start);
  std::vector<double> g(n);
  int iteration = 0;
  while (iteration < s.iterations) {
    ++iteration;
    sample_through(pair.spline, pair.to_deformed, system, warp, g);
    const double g_norm = normalise(g);
    if (!std::isfinite(g_norm)) return Status::not_finite;
    if (g_norm == 0.0) return Status::refinement_failed;
    std::vector<double> b(np, 0.0);
    for (std::size_t i = 0; i < n; ++i)
      for (int j = 0; j < np; ++j) b[j] += steepest[i * np + j] * (g[i] - system.f[i]);
    const std::vector<double> p = lu.solve(b);
    if (!(k == 3 ? compose_affine(warp, p) : compose_quadratic(warp, p))) return Status::refinement_failed;
    const double translation_step = std::max(std::abs(p[0]), std::abs(p[k]));
    double shape_step = 0.0;   // the displacement gradient's step (and, quadratic, its derivatives')
    for (int j = 0; j < np; ++j)
      if (j != 0 && j != k) shape_step = std::max(shape_step, std::abs(p[j]));
    if (translation_step < s.tolerance_px && shape_step < s.tolerance_gradient) break;
  }
  for (double v : warp)
    if (!std::isfinite(v)) return Status::not_finite;
  out.warp = warp;
  out.iterations = iteration;
  return Status::matched;
}

WindowResult match_window_with(Workspace& ws, const Pair& pair, const Settings& s, std::ptrdiff_t row,
                               std::ptrdiff_t col, const bool* used) {
  WindowResult out;
  const std::ptrdiff_t w = s.window_px;
  const std::ptrdiff_t r0 = row - w / 2, c0 = col - w / 2;
  if (r0 < 0 || c0 < 0 || r0 + w > pair.reference.rows || c0 + w > pair.reference.cols) {
    out.status = Status::outside;
    return out;
  }
  std::vector<double> tmpl(w * w);
  double mean = 0.0;
  for (std::ptrdiff_t r = 0; r < w; ++r)
    for (std::ptrdiff_t c = 0; c < w; ++c) mean += tmpl[r * w + c] = pair.reference.at(r0 + r, c0 + c);
  mean /= static_cast<double>(w * w);
  double squares = 0.0;
  for (double v : tmpl) squares += (v - mean) * (v - mean);
  if (!std::isfinite(squares)) {
    out.status = Status::not_finite;
    return out;
  }
  if (std::sqrt(squares / static_cast<double>(w * w)) < 1e-12) {
    out.status = Status::flat;
    return out;
  }

  // the search patch: the deformed image through the prior at every pixel of the search area (dic._correlate_window)
  const std::ptrdiff_t margin = (s.search_px - w) / 2, p = w + 2 * margin;
  std::vector<double> patch(p * p);
  for (std::ptrdiff_t r = 0; r < p; ++r) {
    for (std::ptrdiff_t c = 0; c < p; ++c) {
      const std::ptrdiff_t at_r = r0 - margin + r, at_c = c0 - margin + c;
      double pc = 0.0, pr = 0.0;
      prior_at(pair, at_r, at_c, pc, pr);
      const double x = static_cast<double>(at_c) + pc, y = static_cast<double>(at_r) + pr;
      const auto& motion = pair.to_deformed;
      const double moved_col = motion[0] * x + motion[1] * y + motion[2];
      const double moved_row = motion[3] * x + motion[4] * y + motion[5];
      if (!std::isfinite(moved_col) || !std::isfinite(moved_row)) {
        out.status = Status::not_finite;
        return out;
      }
      patch[r * p + c] = sample_spline(pair.spline, moved_row, moved_col);
    }
  }
  for (double v : patch)
    if (!std::isfinite(v)) {
      out.status = Status::not_finite;
      return out;
    }
  const std::vector<double> score = zncc_map_with(ws, patch, p, tmpl, w);
  const std::ptrdiff_t m = p - w + 1;
  std::ptrdiff_t best = 0;   // the first maximum in row-major order, as numpy's argmax
  for (std::ptrdiff_t k = 1; k < m * m; ++k)
    if (score[k] > score[best]) best = k;
  const std::ptrdiff_t peak_row = best / m, peak_col = best % m;
  const double along_cols = (peak_col == 0 || peak_col == m - 1) ? 0.0 :
      parabola_offset(score[peak_row * m + peak_col - 1], score[best], score[peak_row * m + peak_col + 1]);
  const double along_rows = (peak_row == 0 || peak_row == m - 1) ? 0.0 :
      parabola_offset(score[(peak_row - 1) * m + peak_col], score[best], score[(peak_row + 1) * m + peak_col]);
  out.start = {static_cast<double>(peak_col) + along_cols - static_cast<double>(margin),
               static_cast<double>(peak_row) + along_rows - static_cast<double>(margin)};
  out.peak_score = score[best];
  WindowSystem system;
  out.status = build_system(pair, s, r0, c0, used, system);
  if (out.status == Status::matched) out.status = refine(pair, s, system, out);
  if (pair.errors != nullptr && out.status != Status::not_finite && !system.pixels.empty())
    out.error = window_error(system, *pair.errors, pair.reference, pair.spline, pair.to_deformed,
                             out.status == Status::matched ? &out.warp : nullptr, out.start, out.peak_score);
  return out;
}

}  // namespace

std::vector<double> zncc_map(const std::vector<double>& patch, std::ptrdiff_t p, const std::vector<double>& tmpl,
                             std::ptrdiff_t w) {
  if (w < 1 || p < w || patch.size() != static_cast<std::size_t>(p * p) ||
      tmpl.size() != static_cast<std::size_t>(w * w))
    throw std::invalid_argument("zncc_map: a w x w template inside a p x p patch, p >= w >= 1");
  Workspace ws(next_power_of_two(static_cast<std::size_t>(p)));
  return zncc_map_with(ws, patch, p, tmpl, w);
}

WindowResult match_window(const Pair& pair, const Settings& settings, std::ptrdiff_t row, std::ptrdiff_t col,
                          const bool* used) {
  const std::ptrdiff_t p = settings.window_px + 2 * ((settings.search_px - settings.window_px) / 2);
  Workspace ws(next_power_of_two(static_cast<std::size_t>(p)));
  return match_window_with(ws, pair, settings, row, col, used);
}

std::vector<WindowResult> match_windows(const Pair& pair, const Settings& settings, const std::int64_t* centres,
                                        std::size_t count, const bool* used, int threads) {
  if (settings.window_px < 1 || settings.search_px < settings.window_px || settings.iterations < 0)
    throw std::invalid_argument("match_windows: window_px >= 1, search_px >= window_px and iterations >= 0");
  if (settings.shape_order != 1 && settings.shape_order != 2)
    throw std::invalid_argument("match_windows: the shape function is of order 1 (affine) or 2 (quadratic)");
  if (pair.reference.rows < 1 || pair.reference.cols < 1)
    throw std::invalid_argument("match_windows: the images are empty");
  std::vector<WindowResult> results(count);
  const std::size_t square = static_cast<std::size_t>(settings.window_px) * settings.window_px;
  const std::ptrdiff_t p = settings.window_px + 2 * ((settings.search_px - settings.window_px) / 2);
  const std::size_t side = next_power_of_two(static_cast<std::size_t>(p));
  // windows differ in cost (a failed search stops early), so each thread takes the next one when it is free
  std::atomic<std::size_t> next{0};
  std::exception_ptr failure;
  std::mutex failure_lock;
  auto work = [&]() {
    try {
      Workspace ws(side);
      for (std::size_t k = next++; k < count; k = next++)
        results[k] = match_window_with(ws, pair, settings, static_cast<std::ptrdiff_t>(centres[2 * k]),
                                       static_cast<std::ptrdiff_t>(centres[2 * k + 1]), used + k * square);
    } catch (...) {   // an exception must not leave a thread (std::terminate): the first is rethrown after the join
      std::lock_guard<std::mutex> hold(failure_lock);
      if (!failure) failure = std::current_exception();
      next = count;
    }
  };
  const auto spawned = static_cast<std::size_t>(std::clamp(threads, 1, 256)) - 1;
  std::vector<std::thread> pool;
  pool.reserve(spawned);
  for (std::size_t t = 0; t < std::min(spawned, count); ++t) pool.emplace_back(work);
  work();
  for (auto& thread : pool) thread.join();
  if (failure) std::rethrow_exception(failure);
  return results;
}

}  // namespace calfit::correlation
