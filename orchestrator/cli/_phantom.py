"""Write a phantom case whose loaded image is made by the engine from chosen parameters.

    calfit phantom CASE_DIR [--truth TRUTH_DIR] [--params C10f C10m Kvf Kvm] [--tension T]
                   [--elements 8000] [--order 2] [--points-spacing MM] [--overwrite] [--json] [--quiet]

The phantom calf's own geometry (its labels sampled 4 times finer than the image) is meshed (T6,
8,000 elements by default, finer than any fit mesh), the Avril law with the given parameters (kPa; default Avril et al. Table 2 central values)
is solved under the Laplace-law garment, and the loaded image is rendered by inverse warping with
that displacement. CASE_DIR gets what a user would bring (images, segmentation, landmarks, and
points.csv with measurement noise unless --points-spacing 0: then the images are all there is); the truth (parameters, displacement) goes to TRUTH_DIR
(default CASE_DIR.truth).
"""

from __future__ import annotations

import argparse
import json

from ..model.forward import LEG_PARAMETERS, TABLE2_CENTRAL_KPA
from ..phantom.cases import make_phantom_case
from ._common import (
    add_output_arguments,
    fail,
    folder,
    honours_quiet,
    tension,
    whole_number,
)

HELP = "write a phantom case made by the engine (truth kept apart)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case_dir", type=folder, help="case folder to write")
    parser.add_argument("--truth", help="truth folder (default CASE_DIR.truth)")
    parser.add_argument("--params", type=float, nargs=4, default=list(TABLE2_CENTRAL_KPA),
                        metavar=("C10F", "C10M", "KVF", "KVM"), help="true parameters in kPa (default Table 2 central)")
    parser.add_argument("--tension", type=tension, default=0.16, help="garment tension N/mm (default 0.16, about 20 mmHg)")
    parser.add_argument("--elements", type=whole_number(1), default=8000, help="elements of the engine mesh (default 8000)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=2, help="1: T3, 2: T6 (default)")
    parser.add_argument("--points-spacing", type=float, default=6.0, help="points.csv grid spacing mm (0: none)")
    parser.add_argument("--points-sigma", type=float, default=0.02, help="noise on points.csv displacements, mm")
    parser.add_argument("--overwrite", action="store_true", help="replace existing folders")
    add_output_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        case, truth = make_phantom_case(args.case_dir, args.truth, theta_kPa=args.params, tension_N_per_mm=args.tension,
                                        n_elements=args.elements, order=args.order,
                                        points_spacing_mm=args.points_spacing or None, points_sigma_mm=args.points_sigma,
                                        overwrite=args.overwrite)
    except (FileExistsError, ValueError, RuntimeError) as error:
        return fail(str(error))
    result = {"case_dir": str(case), "truth_dir": str(truth), "parameters_kPa": dict(zip(LEG_PARAMETERS, args.params))}
    print(json.dumps(result) if args.json else f"case written to {case}\ntruth written to {truth}")
    return 0
