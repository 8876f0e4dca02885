"""Measure the displacements of the tissue between the two images (digital image correlation).

    calfit measure CASE_DIR --out RUN_DIR [--window 16|32|64] [--step PX] [--roi-spacing MM] [--prefilter PX]
                   [--respect-outline] [--workers N] [--json] [--quiet]

Slices with pixels finer than 0.18 mm are first averaged over blocks of pixels (reported), so that a window spans
several grains of the texture. Both images are smoothed by a Gaussian of --prefilter pixels (default 1; 0 for
none), which makes the correlation's spline exact on sharp, aliased edges. The loaded image is aligned on the bones
(a rigid motion), then windows of --window pixels (default 32) on a grid inside the leg (every --step pixels,
default half a window) and on the skin, the fascia and the vessels named among the case's landmarks are correlated
in two passes (the second deforms each window by the first pass's field). Windows with a poor match, a large
predicted uncertainty or whose residual exceeds their error model or that fail the normalised median test are
rejected and counted. The error model is calibrated on the windows' residuals (the images' noise, and how far their
edges are drawn from the tissue). For every kept window: its displacement relative to the bones and its 2x2
covariance; overlapping windows' correlation is kept for the fit. With --respect-outline, windows centred inside
the leg leave out the pixels next to its outline and the air beyond (the skin's windows keep them): for images
whose outline carries an error of its own (measured on another program's images: the deep fat's errors then match
their model, at the cost of 3-38 % on the parameters' standard errors; not the default, docs/validation/error-model.md).
Writes RUN_DIR/measurements.csv (every window, kept or why not), measurements.png (the vectors on the image),
measurements.json (summary) and measurements.npz. The windows are matched in --workers processes
(default: 2 or the core count), with the same results as in one.
`calfit identify` runs this itself when the case has no points.csv.
"""

from __future__ import annotations

import argparse
import os

from ..measure.measurements import DEFAULT_WINDOW_PX, DEFAULT_WINDOW_SHAPE, FILES, WINDOW_CHOICES, WINDOW_SHAPES
from ..measure.prefilter import PREFILTER_SIGMA_PX
from ..run.stages import run_measure
from ._common import (
    add_output_arguments,
    emit,
    fail,
    folder,
    honours_quiet,
    positive_number,
    whole_number,
)

HELP = "measure the tissue displacements between the two images (DIC), relative to the bones"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case_dir", help="case folder (case.toml, unloaded and loaded images, optional labels)")
    parser.add_argument("--out", type=folder, required=True, help="run folder (created; later commands use it)")
    parser.add_argument("--window", type=int, choices=WINDOW_CHOICES, default=DEFAULT_WINDOW_PX,
                        help=f"correlation window side in working pixels (default {DEFAULT_WINDOW_PX})")
    parser.add_argument("--window-shape", choices=WINDOW_SHAPES, default=DEFAULT_WINDOW_SHAPE,
                        help=f"the windows' shape function: affine, or quadratic to follow a field that bends inside "
                             f"a window (default {DEFAULT_WINDOW_SHAPE})")
    parser.add_argument("--step", type=whole_number(1), help="grid step in pixels (default half a window)")
    parser.add_argument("--roi-spacing", type=positive_number, help="spacing of the skin and fascia windows in mm (default: the step)")
    parser.add_argument("--prefilter", type=float, default=PREFILTER_SIGMA_PX,
                        help=f"sigma (pixels) of the Gaussian both images are smoothed with (default {PREFILTER_SIGMA_PX:g}; "
                             "0: none)")
    parser.add_argument("--respect-outline", action="store_true",
                        help="windows centred inside the leg leave out its outline and the air beyond (skin windows "
                             "keep them): for an outline drawn with errors of its own")
    parser.add_argument("--workers", type=whole_number(1), default=min(2, os.cpu_count() or 1),
                        help="processes the windows are matched in on this machine (default: 2 or the core count)")
    add_output_arguments(parser)


def summary_lines(summary: dict, run_dir: str) -> list[str]:
    lines = list(summary.get("setup_lines", []))
    lines += [f"DIC: {summary['kept']} of {summary['windows']} {summary.get('window_shape', 'affine')} windows of "
              f"{summary['window_px']} px "
              f"({summary['window_mm']:.1f} mm) kept "
             f"(grid step {summary['step_px']} px; {', '.join(f'{n} {k}' for k, n in summary['kinds'].items())})"]
    lines += [f"  {count:5d}  {status}" for status, count in sorted(summary["status"].items(), key=lambda kv: -kv[1])]
    lines.append(f"image noise {summary['noise_sigma'][0]:.4g} (unloaded) and {summary['noise_sigma'][1]:.4g} (loaded); "
                 f"median standard deviation of a displacement {summary['median_sigma_mm']:.4f} mm; "
                 f"{summary['wall_time_s']:.1f} s")
    if "edge_variance_px2" in summary:
        lines.append(f"error model calibrated on the windows' residuals: noise x{summary['noise_scale']:.2f} in variance "
                     f"against each image's own estimate, edges drawn within "
                     f"{summary['edge_variance_px2'] ** 0.5:.3f} px (prefilter {summary['prefilter_px']:g} px)")
    if summary.get("texture_coherence"):
        lines.append("texture coherence between the slices: " + ", ".join(
            f"{c['tissue']} {c['coherence']:.2f}" for c in summary["texture_coherence"]) + " (1 for the same tissue)")
    if summary.get("through_plane_warning"):
        lines.append(f"warning: {summary['through_plane_warning']}")
    if summary.get("outline_margin_px") is not None:
        lines.append(f"windows inside the leg leave out its outline: the {summary['outline_margin_px']} px next to it and "
                     "the air beyond")
    lines.append(f"written: {', '.join(f'{run_dir}/{name}' for name in FILES.values())}")
    return lines


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        summary = run_measure(args.case_dir, args.out, window_px=args.window, step_px=args.step,
                              roi_spacing_mm=args.roi_spacing, prefilter_px=args.prefilter,
                              respect_outline=args.respect_outline, workers=args.workers,
                              window_shape=args.window_shape)
    except ValueError as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    emit(args, summary, summary_lines(summary, args.out))
    return 0
