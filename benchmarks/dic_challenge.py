"""calfit's DIC windows on the DIC Challenge 2.0 "Star" images: spatial resolution, noise and their product.
Prints figures and saves a figure, asserts nothing.

    PYTHONPATH=. .venv/bin/python benchmarks/dic_challenge.py [--windows 16 32 64] [--step 4] [--images DIR]
                                                             [--shape quadratic|affine] [--prefilter 0]
                                                             [--out benchmarks/figures/dic_challenge.png]

The images. Reu et al., "DIC Challenge 2.0: Developing Images and Guidelines for Evaluating Accuracy and Resolution
of 2D Analyses", Experimental Mechanics 62 (2022), made speckle images deformed by a vertical displacement that is a
sinusoid across the rows whose period grows along the columns (a "star"), with image noise. pyvale (a benchmark
dependency: `pip install pyvale`, which `make bench` does) ships one pair in its package data,
`pyvale/data/dic/challenge/DIC_Challenge_Star_Noise_{Ref,Def}.tiff` (4000 x 501 pixels, 8 bit; taken here for the
Challenge's Star 5); --images reads the same two files from another folder (e.g. pyvale's wheel unzipped).
The commanded field, read off the images with calfit's own windows (a cosine fitted down 8 columns from x = 600 to
3900 px: period 9.8 + 0.0726 x, crest at row 250.0 +- 0.3; the horizontal displacement is noise), is

    v(x, y) = 0.5 cos(2 pi (y - 250) / p(x)),   p(x) = 10 + 0.0725 x   (px; x the column, y the row from the top)

so that along the centre row v sits on its crest, 0.5 px, at every x while the period grows from 10 to 300 px.
A window centred there measures the crest averaged over its height: measured / commanded along that row, against
the period, is the window's transfer function. The Challenge's metrics (Reu et al. 2022, as the iCorrVision-2D
project's validation code describes and applies them; the paper itself was not at hand here):
- spatial resolution l10: the period at which the measured amplitude is attenuated by 10 %. The Challenge's rule
  ("l10 Ch."): a 12th-order polynomial fitted to measured / commanded against the period, where it first rises
  through 0.9. Beside it, the same crossing of the ratio's sliding 100-pixel mean ("l10"), which the figure draws;
- noise n: the standard deviation of the measured displacement along the row on the Challenge's noise-floor image (the
  reference against an image with fresh noise and no motion), which pyvale does not ship. Here ("n zero", for the peer
  table and the Challenge's codes): windows centred a quarter period below the crest, where p >= 200 px, on the
  commanded field's zero crossing, which is odd about them: an affine window reads its error alone there
  (`zero_crossing_noise`). Beside it, the scatter of the crest's measured displacement about its own sliding 100-pixel
  mean ("n scatter": it needs no second row, but takes away the error's components longer than 100 px, and reads 17-28 %
  below n zero at 32-64 px) and about what calfit's observation operator predicts ("n"). Given the Challenge's
  noise-floor image (--noise-image), n is measured on it, as the Challenge does, for both codes;
- the Metrological Efficiency Indicator MEI = n x l10 (px^2): lower is better, and a code cannot lower one of the
  two by changing its window without raising the other. A code's MEI is the mean of its three lowest over the window
  sizes it ran.
The codes that took part are compared by that code MEI: benchmarks/data/dic_challenge_2_star5_code_mei.csv holds the
26 codes' values on Star 5 with their provenance (computed by iCorrVision-2D from the participants' submitted line
cuts and checked there against the paper's figures; not read off the paper here). Their n comes from the
noise-floor image, calfit's and pyvale's from the zero crossing of the same pair: the same images' noise through the
same windows, but not the same pixels, and over the motion of the field's odd part.

What calfit does (`orchestrator.measure.dic.correlate`: ZNCC then IC-GN, quadratic windows by default, --shape affine
for `calfit measure`'s; no prefilter by default, --prefilter 1 for `calfit measure`'s; one pass, no prior; the
search +-10 px about each window, as pyvale's below, `MAX_DISPLACEMENT_PX`) is run
on windows along the centre row every --step pixels for each window size, on a 301-row strip around the centre row
(enough for the 64-pixel windows' search area; the whole image only costs time). Beside it, what the linearised
windows should see of the commanded field (`orchestrator.measure.windows.WindowOperators(...).observe`: the
gradient-weighted affine fit over each window, the observation operator calfit's identification compares its model
with) and, for reference, the textbook limit of an affine window with uniform weights: the mean of the cosine over
its h rows, sin(pi h / p) / (h sin(pi / p)), which is 0.9 at p = 63.8 / 127.7 / 255.6 px for h = 16 / 32 / 64
(67.8 px for a 17-pixel subset).

The ratios are measured (or predicted) / commanded at the window centre (calfit's windows have an even side, so their
centre is half a pixel off the crest), averaged along x over a sliding 100-pixel span (the period changes by 7 px over
it). l10 is the first rise of that curve through 0.9 going to longer periods; "l10 last", the period beyond which it
stays above 0.9, shows how much the noise moves it where the curve runs nearly level with 0.9. The predicted noise is
calfit's covariance (`DICResult.covariance_mm2`, pixel size 1 mm here so mm = px), RMS over the same windows as the
measured noise, with the image noise calfit estimates (`estimate_noise_sigma`) and rescaled to the noise read from
the flat top of the images' power spectrum (`noise_floor`), a check on that estimate.

A peer in the same run: pyvale's own DIC engine (`pyvale.dic.calculate_2d`, C++: subset DIC, ZNSSD, affine shape
function, B-spline interpolation, reliability-guided scan from a seed, its 5-pixel Gaussian prefilter; pyvale's
defaults otherwise, one thread as calfit's windows here) on the same row with odd subsets of one pixel more than
calfit's windows (17 / 33 / 65 px: pyvale takes odd sizes only), so that its subsets are centred on the crest row
itself, and on those nearest to the zero crossing below it. Both codes then go through the same metrics, which need
nothing of either code's own error model: n at the zero crossing, l10 and the plateau as above, MEI = n x l10, the
time of the correlation; and their ratios, calfit / pyvale. The time per window is taken on the same work: pyvale
correlates every subset inside its region of interest, three rows of them about the crest, and calfit is timed again
on those centres, on the same full images, both searching +-10 px (calfit's time includes its error model: each
window's covariance and residual, which pyvale does not compute).

About 5 minutes on a 2-core machine with the defaults (five window sizes, about 1,000 windows each on the crest and
350 on the zero crossing, pyvale's about twice as many).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from orchestrator.measure.dic import COMPILED_ENV, correlate, spline_gradient, windows_module
from orchestrator.measure.prefilter import PREFILTER_SIGMA_PX, Prefilter
from orchestrator.measure.shape import WindowShape
from orchestrator.measure.windows import WindowOperators

AMPLITUDE_PX = 0.5
CREST_ROW = 250
PERIOD_AT_0_PX, PERIOD_SLOPE = 10.0, 0.0725
STRIP_HALF_ROWS = 150            # rows kept on either side of the crest (enough for a 64-px window's default search)
# how far both codes search for a window's match: pyvale's max_displacement, calfit's max_displacement_px (the
# star's motion is half a pixel; the search is most of a window's time, so the two are timed on the same reach)
MAX_DISPLACEMENT_PX = 10
SMOOTH_SPAN_PX = 100             # sliding mean along x of the attenuation
NOISE_MIN_PERIOD_PX = 200.0      # where the noise is measured
PLATEAU_MIN_PERIOD_PX = 250.0    # where the plateau is read
LEVEL = 0.9                      # 10 % attenuation
IMAGE_NAMES = ("DIC_Challenge_Star_Noise_Ref.tiff", "DIC_Challenge_Star_Noise_Def.tiff")

CHALLENGE_POLYNOMIAL_DEGREE = 12   # the Challenge fits its attenuation curves with a 12th-order polynomial
CODE_MEI_LOWEST = 3                # and summarises a code by the mean of its three lowest MEIs
PARTICIPANTS_CSV = Path(__file__).resolve().parent / "data" / "dic_challenge_2_star5_code_mei.csv"


def participants() -> list[tuple[str, str, float]]:
    """(code, family, code MEI px^2) of the Challenge's codes on Star 5 (provenance in the file's header)."""
    import csv

    with open(PARTICIPANTS_CSV, newline="") as table:
        rows = csv.DictReader(line for line in table if not line.startswith("#"))
        return [(row["code"], row["family"], float(row["code_mei_px2"])) for row in rows]


def challenge_l10(period: np.ndarray, ratio: np.ndarray) -> float:
    """The Challenge's spatial resolution: where a 12th-order polynomial fitted to measured / commanded against the
    period first rises through 0.9 (Polynomial.fit maps the periods onto [-1, 1], where that degree is well posed)."""
    ok = np.isfinite(period) & np.isfinite(ratio)
    polynomial = np.polynomial.Polynomial.fit(period[ok], ratio[ok], CHALLENGE_POLYNOMIAL_DEGREE)
    fine = np.linspace(period[ok].min(), period[ok].max(), 20000)
    return first_crossing(fine, polynomial(fine))


def code_mei(meis) -> float:
    """A code's MEI as the Challenge ranks codes: the mean of its three lowest over the window sizes it ran."""
    finite = np.sort(np.asarray(meis, float)[np.isfinite(meis)])
    return float(finite[:CODE_MEI_LOWEST].mean()) if finite.size >= CODE_MEI_LOWEST else float("nan")


def peer_step(subset: int, step: int) -> int:
    """pyvale puts its subsets' corners at multiples of the step, so its centres at k step + subset // 2: the largest
    step up to `step` that puts a row of them on the crest."""
    return max(d for d in range(1, step + 1) if (CREST_ROW - subset // 2) % d == 0)


def pyvale_run(reference: np.ndarray, deformed: np.ndarray, subset: int, step: int, roi: np.ndarray, seed_x: int,
               scratch: Path, tag: str) -> tuple[dict, float]:
    """pyvale's DIC (`pyvale.dic.calculate_2d`, its defaults but the subset, the step, one thread and a 10-pixel
    search) on a region of interest, from a seed at x = seed_x px inside it: its result columns and seconds."""
    import pyvale.dic

    rows = np.flatnonzero(roi[:, seed_x])
    out = scratch / f"pyvale-{tag}-{subset}"
    out.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    pyvale.dic.calculate_2d(reference=reference.astype(np.float32), deformed=deformed.astype(np.float32),
                            roi_mask=roi, seed=[seed_x, int(rows[len(rows) // 2])], subset_size=subset,
                            subset_step=step, max_displacement=MAX_DISPLACEMENT_PX, num_threads=1, output_basepath=out,
                            print_level=0)
    seconds = time.perf_counter() - began
    path = next(out.glob("dic_results_*.csv"))
    with open(path) as table:   # a quoted header whose lines, like the rows, end with a comma
        names = [name.strip('"') for name in table.readline().strip().rstrip(",").split(",")]
    columns = dict(zip(names, np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(len(names)), ndmin=2).T))
    columns["disp_v"] = np.where(columns["converged"] > 0, columns["disp_v"], np.nan)
    return columns, seconds


def pyvale_crest(reference: np.ndarray, deformed: np.ndarray, subset: int, step: int, scratch: Path,
                 noise_image: np.ndarray | None = None) -> dict:
    """pyvale on the subsets centred on the crest row, from a seed at x = 3500 px (where the period is long, as in
    pyvale's own example on these images), and on those nearest to the zero crossing below it where p >= 200 px (for
    the noise, `zero_crossing_noise`), and, given the Challenge's noise-floor image, on the crest row of the
    reference against it: x, v, converged, the crest's correlation seconds and the metrics."""
    step = peer_step(subset, step)
    half = subset // 2
    roi = np.zeros(reference.shape, dtype=bool)
    roi[CREST_ROW - half - step:CREST_ROW + half + step + 1, 40:reference.shape[1] - 40] = True
    columns, seconds = pyvale_run(reference, deformed, subset, step, roi, 3500, scratch, "crest")
    crest = columns["subset_y"] == CREST_ROW
    if not crest.any():
        sys.exit(f"dic_challenge: pyvale put no {subset}-px subset on row {CREST_ROW}")
    order = np.argsort(columns["subset_x"][crest])
    v = columns["disp_v"][crest][order]
    x = columns["subset_x"][crest][order]
    metrics = common_metrics(x, CREST_ROW, v, step)

    # a band following the zero crossing, tall enough to hold a row of subsets at any step
    all_x = np.arange(reference.shape[1])
    band = ((np.abs(np.arange(reference.shape[0])[:, None] - zero_row(all_x)[None, :]) <= half + 2 * step + 3)
            & (period_px(all_x) >= NOISE_MIN_PERIOD_PX)[None, :])
    band[:, reference.shape[1] - 40:] = False
    zero, _ = pyvale_run(reference, deformed, subset, step, band, 3500, scratch, "zero")
    nearest = {}   # per x, the subset centred nearest to the zero crossing
    for zx, zy, zv in zip(zero["subset_x"], zero["subset_y"], zero["disp_v"]):
        if zx not in nearest or abs(zy - zero_row(zx)) < abs(nearest[zx][0] - zero_row(zx)):
            nearest[zx] = (zy, zv)
    zx = np.array(sorted(nearest))
    zy, zv = (np.array([nearest[k][i] for k in zx]) for i in (0, 1))
    noise_floor_image = float("nan")
    if noise_image is not None:
        still, _ = pyvale_run(reference, noise_image, subset, step, roi, 3500, scratch, "floor")
        noise_floor_image = float(np.nanstd(still["disp_v"][still["subset_y"] == CREST_ROW]))
    # pyvale correlates every subset inside the region, three rows of them here: its time is theirs, not the crest's,
    # and calfit is timed on the same centres (`time_on_centres`)
    return dict(subset=subset, step=step, x=x, v=v, failed=int(np.isnan(v).sum()), seconds=seconds,
                centres=np.column_stack([columns["subset_y"], columns["subset_x"]]).astype(int),
                noise_zero=zero_crossing_noise(zx, zy, zv, x, metrics["ratio"]),
                noise_floor_image=noise_floor_image, **metrics)


def time_on_centres(reference: np.ndarray, deformed: np.ndarray, window: int, centres: np.ndarray,
                    shape: WindowShape, prefilter: Prefilter) -> float:
    """Seconds calfit's `correlate` takes for windows of `window` px at the (row, column) `centres` of pyvale's
    subsets on the same images: the two codes timed on the same work (a code's time per window falls with the
    windows it shares its images' preparation among)."""
    began = time.perf_counter()
    correlate(reference, deformed, centres, (1.0, 1.0), window_px=window, shape=shape, prefilter=prefilter,
              max_displacement_px=MAX_DISPLACEMENT_PX)
    return time.perf_counter() - began


def zero_row(x) -> np.ndarray:
    """The row where the commanded displacement crosses zero, a quarter period below the crest."""
    return CREST_ROW + period_px(x) / 4.0


def zero_crossing_noise(x, y, v, crest_x, crest_ratio) -> float:
    """n from windows centred where the commanded displacement crosses zero, where p >= 200 px: the field is odd
    about their centre, which an affine window takes whole (up to its cubic term), so what they read is their error
    alone, as on the Challenge's noise-floor image, which has no motion. A centre off the crossing by d sees the
    cosine's even part 0.5 sin(2 pi d / p), attenuated as the crest is: that is taken off with the crest's
    measured / commanded ratio (its sliding mean) at the same x. Windows on the crest and the trough, paired, read
    45-80 % more at 64 px (0.0035-0.0041 px against 0.0023-0.0024): the speckle under each weights the crest's
    curvature its own way, an error of the displacement's shape, which a field without motion does not have.
    Checked against a noise-floor pair made of the reference and the reference plus fresh noise of the images' sigma
    (2.2 grey levels: one image's noise where the Challenge's pair has two): 16-pixel windows read 0.0079 px on it
    (pyvale's 17-pixel subsets 0.0073), and 0.0112 (0.0103) at the zero crossing, sqrt(2) times as much."""
    x, y, v = (np.asarray(a, float) for a in (x, y, v))
    long = (period_px(x) >= NOISE_MIN_PERIOD_PX) & np.isfinite(v)
    attenuation = np.interp(x[long], crest_x[np.isfinite(crest_ratio)], crest_ratio[np.isfinite(crest_ratio)])
    error = v[long] - attenuation * commanded_v(x[long], y[long])
    return float(np.std(error)) if error.size > 10 else float("nan")


def common_metrics(x: np.ndarray, y, v: np.ndarray, step: int) -> dict:
    """The metrics both codes go through (module text): the attenuation ratio along the period, n about the sliding
    mean ("noise"; `analyse` keeps it as "noise_scatter" beside its own n), l10 and MEI on the sliding mean, l10 by
    the Challenge's rule, plateau."""
    period = period_px(x)
    span = max(SMOOTH_SPAN_PX // step, 1)
    ratio = sliding_mean(v / commanded_v(x, y), span)
    long = (period >= NOISE_MIN_PERIOD_PX) & np.isfinite(v)
    noise = float(np.std((v - sliding_mean(v, span))[long]))
    l10 = first_crossing(period, ratio)
    l10_challenge = challenge_l10(period, v / commanded_v(x, y))
    return dict(period=period, ratio=ratio, noise=noise, l10=l10, mei=noise * l10, l10_challenge=l10_challenge,
                plateau=float(np.nanmean(v[period >= PLATEAU_MIN_PERIOD_PX])))


def period_px(x) -> np.ndarray:
    return PERIOD_AT_0_PX + PERIOD_SLOPE * np.asarray(x, float)


def commanded_v(x, y) -> np.ndarray:
    return AMPLITUDE_PX * np.cos(2.0 * np.pi * (np.asarray(y, float) - CREST_ROW) / period_px(x))


def uniform_window(h: int, period) -> np.ndarray:
    """Attenuation of a cosine's crest by an affine window of h rows with uniform weights (the mean over the rows)."""
    period = np.asarray(period, float)
    return np.sin(np.pi * h / period) / (h * np.sin(np.pi / period))


def pyvale_images_folder() -> Path:
    spec = importlib.util.find_spec("pyvale")   # finds the package without importing it (pyvale's import is slow)
    if spec is None or not spec.submodule_search_locations:
        sys.exit("dic_challenge: the Star images come with pyvale, which is not installed in this environment.\n"
                 "  Install it:  .venv/bin/python -m pip install pyvale   (make bench does)\n"
                 "  or unpack its wheel (pip download pyvale --no-deps; unzip) and pass "
                 "--images .../pyvale/data/dic/challenge")
    return Path(list(spec.submodule_search_locations)[0]) / "data" / "dic" / "challenge"


def load_star(folder: Path | None) -> tuple[np.ndarray, np.ndarray]:
    folder = pyvale_images_folder() if folder is None else Path(folder)
    paths = [folder / name for name in IMAGE_NAMES]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        sys.exit("dic_challenge: missing " + ", ".join(missing) + " (pyvale's package data: data/dic/challenge)")
    reference, deformed = (load_image(p) for p in paths)
    return reference, deformed


def load_image(path: Path) -> np.ndarray:
    from PIL import Image

    if not Path(path).is_file():
        sys.exit(f"dic_challenge: no image at {path}")
    return np.asarray(Image.open(path), dtype=float)


def sliding_mean(values: np.ndarray, span: int) -> np.ndarray:
    """NaN-aware mean over `span` neighbours (centred); NaN where none is finite."""
    finite = np.isfinite(values)
    kernel = np.ones(max(int(span), 1))
    total = np.convolve(np.where(finite, values, 0.0), kernel, mode="same")
    count = np.convolve(finite.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def first_crossing(period: np.ndarray, ratio: np.ndarray, level: float = LEVEL) -> float:
    """The shortest period at which the curve rises through `level` (interpolated); NaN if it never does."""
    ok = np.isfinite(ratio)
    period, ratio = period[ok], ratio[ok]
    up = np.flatnonzero((ratio[:-1] < level) & (ratio[1:] >= level))
    if up.size == 0:
        return float("nan")
    i = int(up[0])
    p0, p1, r0, r1 = period[i], period[i + 1], ratio[i], ratio[i + 1]
    return float(p0 + (level - r0) * (p1 - p0) / (r1 - r0))


def last_crossing(period: np.ndarray, ratio: np.ndarray, level: float = LEVEL) -> float:
    """The period beyond which the curve stays at or above `level` (interpolated); NaN if it ends below it."""
    ok = np.isfinite(ratio)
    period, ratio = period[ok], ratio[ok]
    below = np.flatnonzero(ratio < level)
    if below.size == 0 or below[-1] == len(ratio) - 1:
        return float("nan")
    i = int(below[-1])
    p0, p1, r0, r1 = period[i], period[i + 1], ratio[i], ratio[i + 1]
    return float(p0 + (level - r0) * (p1 - p0) / (r1 - r0))


def noise_floor(image: np.ndarray, from_cycles_per_px: float = 0.4) -> float:
    """Standard deviation of white image noise from the flat top of the image's power spectrum (Hann-windowed),
    where max(|kx|, |ky|) >= from_cycles_per_px: the speckle's own power has died out there on these images. A
    check on calfit's estimator (`estimate_noise_sigma`), whose calm half of an image that is speckle everywhere
    still holds texture."""
    taper = np.outer(np.hanning(image.shape[0]), np.hanning(image.shape[1]))
    power = np.abs(np.fft.fft2((image - image.mean()) * taper)) ** 2 / (image.size * np.mean(taper ** 2))
    ky = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    kx = np.abs(np.fft.fftfreq(image.shape[1]))[None, :]
    return float(np.sqrt(power[np.maximum(kx, ky) >= from_cycles_per_px].mean()))


def observe_in_chunks(reference, gradients, centres, window, noise_sigma, field, shape: WindowShape,
                      prefilter: Prefilter, chunk: int = 200) -> np.ndarray:
    """WindowOperators(...).observe(field) a few hundred windows at a time (a 64-px window holds 16 kB of weights)."""
    out = []
    for start in range(0, len(centres), chunk):
        operators = WindowOperators(reference, centres[start:start + chunk], window, (1.0, 1.0), noise_sigma,
                                    gradients=gradients, window_shape=shape, prefilter=prefilter)
        out.append(operators.observe(field))
    return np.concatenate(out)


def analyse(reference, deformed, gradients, field, window: int, step: int, row0: int, full_reference,
            full_deformed, shape: WindowShape, prefilter: Prefilter, noise_image: np.ndarray | None = None) -> dict:
    """Measured and predicted displacement along the crest for one window size, the Challenge's metrics, the noise
    at the zero crossing below the crest (on the full images, whose rows the strip may not hold) and, given the
    Challenge's noise-floor image (the same speckle, fresh noise, no motion), the Challenge's n itself: the standard
    deviation of v along the crest row of the reference against it."""
    width = reference.shape[1]
    crest = CREST_ROW - row0
    columns = np.arange(window // 2, width - window // 2 + 1, step)
    centres = np.column_stack([np.full(len(columns), crest), columns])
    began = time.perf_counter()
    # one pass, no prior: the windows' own covariance under the images' noise, not calibrated on their residuals,
    # which here hold the misfit of an affine window to periods shorter than a few windows (`calfit measure` deforms
    # its windows by a first pass's field before it calibrates)
    result = correlate(reference, deformed, centres, (1.0, 1.0), window_px=window, shape=shape, prefilter=prefilter,
                       max_displacement_px=MAX_DISPLACEMENT_PX)
    seconds_dic = time.perf_counter() - began
    began = time.perf_counter()
    seen = observe_in_chunks(reference, gradients, centres, window, result.noise_sigma[0], field, shape,
                             prefilter)[:, 1]
    seconds_operator = time.perf_counter() - began

    x = result.centre_rc[:, 1]
    y = result.centre_rc[:, 0] + row0
    period = period_px(x)
    commanded = commanded_v(x, y)
    measured = result.displacement_px[:, 1]
    failed = ~np.isfinite(measured) | ~np.all(np.isfinite(result.covariance_mm2), axis=(1, 2))
    measured = np.where(failed, np.nan, measured)
    sigma = np.sqrt(np.where(failed, np.nan, result.covariance_mm2[:, 1, 1]))   # pixel = 1 mm

    common = common_metrics(x, y, measured, step)
    columns_long = columns[period_px(columns) >= NOISE_MIN_PERIOD_PX]
    zero = correlate(full_reference, full_deformed, np.column_stack([np.rint(zero_row(columns_long)), columns_long]),
                     (1.0, 1.0), window_px=window, shape=shape, prefilter=prefilter,
                     max_displacement_px=MAX_DISPLACEMENT_PX)
    noise_zero = zero_crossing_noise(zero.centre_rc[:, 1], zero.centre_rc[:, 0], zero.displacement_px[:, 1], x,
                                     common["ratio"])
    noise_floor_image = float("nan")
    if noise_image is not None:
        still = correlate(reference, noise_image[row0:row0 + reference.shape[0]], centres, (1.0, 1.0),
                          window_px=window, shape=shape, prefilter=prefilter, max_displacement_px=MAX_DISPLACEMENT_PX)
        noise_floor_image = float(np.nanstd(still.displacement_px[:, 1]))
    ratio_measured = common["ratio"]
    ratio_seen = sliding_mean(seen / commanded, max(SMOOTH_SPAN_PX // step, 1))
    long = period >= NOISE_MIN_PERIOD_PX
    residual = (measured - seen)[long]
    residual = residual[np.isfinite(residual)]
    noise = float(np.std(residual))
    noise_predicted = float(np.sqrt(np.nanmean(sigma[long] ** 2)))
    l10 = common["l10"]
    fine = np.linspace(period.min(), period.max(), 20000)
    plateau = period >= PLATEAU_MIN_PERIOD_PX
    gap = np.abs(ratio_measured - ratio_seen)
    gap[period < 2 * window] = np.nan    # where the windows see almost nothing, the ratio is noise over a tiny signal
    worst = int(np.nanargmax(gap))
    return dict(window=window, step=step, x=x, period=period, commanded=commanded, measured=measured, seen=seen,
                sigma=sigma, noise_scatter=common["noise"], noise_zero=noise_zero, noise_floor_image=noise_floor_image,
                ratio_measured=ratio_measured, l10_challenge=common["l10_challenge"], ratio_seen=ratio_seen,
                failed=int(failed.sum()), windows=len(x),
                noise=noise, noise_predicted=noise_predicted, noise_sigma=result.noise_sigma[0], l10=l10,
                l10_last=last_crossing(period, ratio_measured), l10_seen=first_crossing(period, ratio_seen),
                l10_uniform=first_crossing(fine, uniform_window(window, fine)), mei=noise * l10,
                plateau=common["plateau"], plateau_seen=float(np.mean(seen[plateau])),
                gap=float(gap[worst]), gap_period=float(period[worst]), seconds_dic=seconds_dic,
                seconds_operator=seconds_operator, zncc=float(np.median(result.confidence)))


BANDS_PX = ((10, 20), (20, 40), (40, 80), (80, 150), (150, 300))


def report(results: list[dict], floor_sigma: float) -> None:
    print(f"\nDIC Challenge 2.0 Star images, crest row {CREST_ROW}, commanded {AMPLITUDE_PX} px, period "
          f"{PERIOD_AT_0_PX:g} + {PERIOD_SLOPE:g} x px; n from p >= {NOISE_MIN_PERIOD_PX:g} px, plateau p >= "
          f"{PLATEAU_MIN_PERIOD_PX:g} px")
    print(f"{'window':>7s} {'windows':>8s} {'failed':>6s} {'n px':>7s} {'n pred':>7s} {'@floor':>7s} {'l10 px':>7s} "
          f"{'l10 last':>8s} {'l10 op':>7s} {'l10 unif':>8s} {'MEI px2':>8s} {'plateau':>8s} {'plat op':>8s} "
          f"{'ZNCC':>6s} {'DIC s':>6s} {'op s':>5s}")
    for r in results:
        print(f"{r['window']:5d}px {r['windows']:8d} {r['failed']:6d} {r['noise']:7.4f} {r['noise_predicted']:7.4f} "
              f"{r['noise_predicted'] * floor_sigma / r['noise_sigma']:7.4f} {r['l10']:7.1f} {r['l10_last']:8.1f} "
              f"{r['l10_seen']:7.1f} {r['l10_uniform']:8.1f} {r['mei']:8.3f} {r['plateau']:8.4f} "
              f"{r['plateau_seen']:8.4f} {r['zncc']:6.3f} {r['seconds_dic']:6.1f} {r['seconds_operator']:5.1f}")
    sigma = results[0]["noise_sigma"]
    print(f"  n: std of measured - operator prediction; n pred: calfit's covariance (RMS sigma) with calfit's image "
          f"noise {sigma:.3f} grey levels; @floor: the same with the noise of the spectrum's flat top, "
          f"{floor_sigma:.3f} (scaled); l10: first rise through 0.9 of the measured curve, l10 last: beyond which it "
          f"stays above 0.9; l10 op / unif: first rise of the operator's prediction / of a uniform affine window; "
          f"MEI = n x l10")
    for r in results:
        print(f"  {r['window']:2d} px: largest gap between the measured and the predicted attenuation "
              f"(p >= 2 windows): {r['gap']:.3f} at p = {r['gap_period']:.0f} px")

    print("\nmeasured - operator prediction of v (px) by period band: mean (std) over the windows")
    print(f"{'window':>7s} " + " ".join(f"{f'{a}-{b} px':>16s}" for a, b in BANDS_PX))
    for r in results:
        cells = []
        for a, b in BANDS_PX:
            band = (r["period"] >= a) & (r["period"] < b)
            d = (r["measured"] - r["seen"])[band]
            d = d[np.isfinite(d)]
            cells.append(f"{np.mean(d):+8.4f} ({np.std(d):.4f})" if d.size else f"{'-':>16s}")
        print(f"{r['window']:5d}px " + " ".join(f"{c:>16s}" for c in cells))


def report_participants(results: list[dict], peers: list[dict]) -> dict:
    """calfit's and pyvale's code MEI (the Challenge's l10 rule, n on the Challenge's noise-floor image when given,
    else at the zero crossing, the three lowest of their window sizes) placed among the Challenge's codes; returns
    the two code MEIs and where their n comes from, for the figure."""
    codes = participants()
    theirs = np.array([mei for _, _, mei in codes])
    on_image = all(np.isfinite(r["noise_floor_image"]) for r in results + peers)
    used = "noise_floor_image" if on_image else "noise_zero"
    source = ("the noise-floor image's crest row, as the Challenge measures it" if on_image else
              f"windows on the zero crossing where p >= {NOISE_MIN_PERIOD_PX:g} px (the noise-floor image not given)")
    print(f"\nbeside the {len(codes)} codes of the DIC Challenge 2.0 on Star 5 (their code MEI: "
          f"{PARTICIPANTS_CSV.relative_to(PARTICIPANTS_CSV.parents[2])}); n from {source}, the scatter beside it; "
          "l10 Ch. by the Challenge's rule; MEI = n x l10 Ch.:")
    print(f"{'code':>8s} {'window':>7s} {'n scatter':>9s} {'n zero':>8s} {'n image':>8s} {'l10 Ch.':>8s} "
          f"{'MEI px2':>8s}")
    ours = {}
    for code, runs, size in (("calfit", results, "window"), ("pyvale", peers, "subset")):
        meis = []
        for r in runs:
            scatter = r["noise_scatter"] if code == "calfit" else r["noise"]
            meis.append(r[used] * r["l10_challenge"])
            print(f"{code:>8s} {r[size]:5d}px {scatter:9.4f} {r['noise_zero']:8.4f} {r['noise_floor_image']:8.4f} "
                  f"{r['l10_challenge']:8.1f} {meis[-1]:8.3f}")
        ours[code] = code_mei(meis)
    print(f"  the Challenge's codes: median {np.median(theirs):.3f} px^2, quartiles {np.quantile(theirs, 0.25):.3f}-"
          f"{np.quantile(theirs, 0.75):.3f}, range {theirs.min():.3f}-{theirs.max():.3f}; by family:")
    for family in dict.fromkeys(f for _, f, _ in codes):
        values = np.array([mei for _, f, mei in codes if f == family])
        print(f"    {family:>16s}: {len(values):2d} codes, {values.min():.3f}-{values.max():.3f} px^2")
    for code, mei in ours.items():
        if not np.isfinite(mei):
            print(f"  {code}: fewer than {CODE_MEI_LOWEST} window sizes with an l10, no code MEI (run --windows with "
                  f"{CODE_MEI_LOWEST} or more)")
            continue
        lower = int(np.sum(theirs < mei))
        print(f"  {code} (mean of its {CODE_MEI_LOWEST} lowest): code MEI {mei:.3f} px^2, "
              f"{mei / np.median(theirs):.2f} x the participants' median; {lower} of the {len(codes)} codes lower, "
              f"rank {lower + 1} of {len(codes) + 1}")
    return ours, ("n on the Challenge's noise-floor image" if on_image else
                  "their n at the zero crossing of the same pair (the noise-floor image is not in pyvale's)")


def report_peer(results: list[dict], peers: list[dict]) -> None:
    """Both codes through the same metrics, which need neither code's error model (n at the zero crossing, l10 on
    the sliding mean, MEI = n x l10), with calfit / pyvale ratios."""
    print("\nbeside pyvale's DIC engine (same images, same row, one thread each; the same metrics for both, which "
          "need neither code's error model: n at the zero crossing below the crest where p >= "
          f"{NOISE_MIN_PERIOD_PX:g} px, l10 of the sliding mean; the time of both on pyvale's subsets, the crest's "
          f"rows, searched +-{MAX_DISPLACEMENT_PX} px)")
    print(f"{'code':>8s} {'subset':>7s} {'step':>5s} {'windows':>8s} {'failed':>6s} {'n px':>7s} {'l10 px':>7s} "
          f"{'MEI px2':>8s} {'plateau':>8s} {'DIC s':>6s}")
    for r, peer in zip(results, peers):
        rows = []
        count = len(peer["centres"])   # both timed on pyvale's subsets (`time_on_centres`)
        for code, size, m, seconds in (("calfit", r["window"], r, r["seconds_same"]),
                                       ("pyvale", peer["subset"], peer, peer["seconds"])):
            rows.append((m["noise_zero"], m["l10"], m["noise_zero"] * m["l10"], seconds / count))
            print(f"{code:>8s} {size:5d}px {m['step']:5d} {count:8d} {m['failed']:6d} {rows[-1][0]:7.4f} "
                  f"{rows[-1][1]:7.1f} {rows[-1][2]:8.3f} {m['plateau']:8.4f} {seconds:6.1f}")
        (n, l10, mei, per_window), (n_peer, l10_peer, mei_peer, per_window_peer) = rows
        print(f"{'calfit / pyvale':>22s}: n {n / n_peer:.2f} x, l10 {l10 / l10_peer:.2f} x, MEI "
              f"{mei / mei_peer:.2f} x, time per window {per_window / per_window_peer:.2f} x")


def figure(results: list[dict], out: Path, peers: list[dict], code_meis: dict, noise_source: str,
           shape: WindowShape) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")
    fig, (top, bottom, ranking) = plt.subplots(3, 1, figsize=(9, 11.5), gridspec_kw=dict(height_ratios=(1, 1.4, 0.7)))
    for r, colour in zip(results, colours):
        top.plot(r["x"], r["measured"], color=colour, lw=0.6, label=f"{r['window']} px windows")
    top.plot(results[0]["x"], results[0]["commanded"], color="black", lw=1.0, ls="--", label="commanded")
    top.set_xlabel("x along the crest row (px)")
    top.set_ylabel("measured v (px)")
    top.set_ylim(-0.1, 0.7)
    top.set_xlim(0, 4000)
    periods = top.secondary_xaxis("top", functions=(period_px, lambda p: (p - PERIOD_AT_0_PX) / PERIOD_SLOPE))
    periods.set_xlabel("period p (px)")
    top.legend(loc="lower right", fontsize=8, ncol=2)
    top.set_title(f"calfit DIC, {shape.name} windows, on the DIC Challenge 2.0 Star images (crest row, amplitude "
                  "0.5 px);\nbelow, pyvale's beside it", fontsize=10)

    for r, colour in zip(results, colours):
        bottom.plot(r["period"], r["ratio_measured"], color=colour, lw=1.6,
                    label=f"{r['window']} px: measured, l10 = {r['l10']:.0f} px")
        bottom.plot(r["period"], r["ratio_seen"], color=colour, lw=1.2, ls="--",
                    label=f"{r['window']} px: observation operator, l10 = {r['l10_seen']:.0f} px")
        bottom.plot(r["period"], uniform_window(r["window"], r["period"]), color=colour, lw=0.8, ls=":")
    for peer, colour in zip(peers, colours):
        bottom.plot(peer["period"], peer["ratio"], color=colour, lw=0.9, ls="-.",
                    label=f"pyvale {peer['subset']} px subsets: measured, l10 = {peer['l10']:.0f} px")
    bottom.plot([], [], color="grey", lw=0.8, ls=":", label="uniform affine window (textbook)")
    bottom.axhline(LEVEL, color="black", lw=0.8)
    bottom.text(295, LEVEL + 0.01, "10 % attenuation", ha="right", va="bottom", fontsize=8)
    bottom.set_xlim(0, 300)
    bottom.set_ylim(0.0, 1.1)
    bottom.set_xlabel("period p (px)")
    bottom.set_ylabel("measured / commanded amplitude")
    bottom.grid(alpha=0.3)
    bottom.legend(loc="lower right", fontsize=7.5)

    codes = participants()
    families = list(dict.fromkeys(family for _, family, _ in codes))
    for row, family in enumerate(families):
        values = [mei for _, f, mei in codes if f == family]
        ranking.plot(values, np.full(len(values), row), "o", color="grey", ms=5, alpha=0.7)
    for code, colour in (("calfit", "tab:blue"), ("pyvale", "tab:red")):
        if not np.isfinite(code_meis[code]):
            continue
        ranking.axvline(code_meis[code], color=colour, lw=1.2, ls="--")
        ranking.plot([], [], ls="--", color=colour, label=f"{code}: {code_meis[code]:.2f} px$^2$")
    ranking.axvline(np.median([mei for _, _, mei in codes]), color="black", lw=0.8, ls=":")
    ranking.plot([], [], ls=":", color="black", label="median of the Challenge's codes")
    ranking.set_yticks(range(len(families)), [f"{f} ({sum(1 for c in codes if c[1] == f)})" for f in families])
    ranking.set_ylim(-0.6, len(families) - 0.4)
    ranking.set_xlabel(f"code MEI = n x l10, mean of the three lowest window sizes (px$^2$; lower is better)\n"
                       f"calfit and pyvale: {noise_source}", fontsize=9)
    ranking.set_title("The DIC Challenge 2.0 codes' displacement MEI on Star 5 (Reu et al. 2022), calfit's and "
                      "pyvale's among them", fontsize=10)
    ranking.grid(alpha=0.3, axis="x")
    ranking.legend(loc="upper right", fontsize=7.5)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"\nfigure: {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--windows", type=int, nargs="+", default=[16, 24, 32, 48, 64], help="window sides, px")
    parser.add_argument("--step", type=int, default=4, help="pixels between window centres along the crest row")
    parser.add_argument("--images", type=Path, default=None, help="folder holding the two Star TIFFs "
                        "(default: pyvale's package data)")
    parser.add_argument("--noise-image", type=Path, default=None, help="the Challenge's noise-floor image of Star 5 "
                        "(DIC_Challenge_Star_Noise.tif from its site; pyvale does not ship it): n is then measured as "
                        "the Challenge measures it, for both codes")
    parser.add_argument("--shape", choices=("affine", "quadratic"), default="quadratic",
                        help="calfit's window shape function (orchestrator.measure.shape; default quadratic, the "
                        "shape of the Challenge's best codes)")
    # calfit measure's one-pixel prefilter is there for the aliased edges that partial volume draws on an MRI slice;
    # a camera's speckle is band-limited by its optics and has none, so the Star images are matched unfiltered
    parser.add_argument("--prefilter", type=float, default=0.0,
                        help="sigma (px) of the Gaussian calfit smooths both images with (default 0: camera speckle "
                             f"has no partial-volume edges; `calfit measure`'s default for MRI is {PREFILTER_SIGMA_PX:g})")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/figures/dic_challenge.png"))
    args = parser.parse_args()
    shape = WindowShape.named(args.shape)
    prefilter = Prefilter(args.prefilter)

    full_reference, full_deformed = load_star(args.images)
    noise_image = None if args.noise_image is None else load_image(args.noise_image)
    row0 = CREST_ROW - STRIP_HALF_ROWS
    reference = full_reference[row0:CREST_ROW + STRIP_HALF_ROWS + 1]
    deformed = full_deformed[row0:CREST_ROW + STRIP_HALF_ROWS + 1]
    rows, cols = np.mgrid[0:reference.shape[0], 0:reference.shape[1]]
    field = np.stack([np.zeros(reference.shape), commanded_v(cols, rows + row0)])   # (u_x, u_y), px = mm here
    gradients = spline_gradient(prefilter(reference))   # the windows' operators read the prefiltered reference
    floor_sigma = float(np.sqrt(0.5 * (noise_floor(reference) ** 2 + noise_floor(deformed) ** 2)))
    print(f"Star images {reference.shape[1]} px wide, rows {row0}-{row0 + reference.shape[0] - 1} kept; windows "
          f"{', '.join(map(str, args.windows))} px every {args.step} px along row {CREST_ROW}")
    loops = ("the compiled loops (orchestrator._correlation)" if windows_module() is not None
             else f"the Python loops ({COMPILED_ENV}=0 or no compiled module)")
    print(f"calfit's windows: {shape.name}, prefilter {prefilter.sigma_px:g} px, {loops}")
    results = []
    for window in args.windows:
        results.append(analyse(reference, deformed, gradients, field, window, args.step, row0, full_reference,
                               full_deformed, shape, prefilter, noise_image))
        r = results[-1]
        print(f"  {window:2d} px: {r['windows']} windows, DIC {r['seconds_dic']:.1f} s, operator "
              f"{r['seconds_operator']:.1f} s", flush=True)
    report(results, floor_sigma)
    with tempfile.TemporaryDirectory(prefix="calfit-pyvale-") as scratch:
        peers = [pyvale_crest(full_reference, full_deformed, window + 1, args.step, Path(scratch), noise_image)
                 for window in args.windows]
    for r, peer in zip(results, peers):
        r["seconds_same"] = time_on_centres(full_reference, full_deformed, r["window"], peer["centres"], shape,
                                            prefilter)
    report_peer(results, peers)
    code_meis, noise_source = report_participants(results, peers)
    figure(results, args.out, peers, code_meis, noise_source, shape)


if __name__ == "__main__":
    main()
