"""The k-space phantom's costs and its departure from plane strain: a 3D solve, one case, 3D against 2D.

    cd /work/main && .venv/bin/python benchmarks/kspace3d_phantom.py [--fine] [--deformed] [--no-case]

Solves the default 3D leg (`orchestrator.phantom.kspace3d`: 1,000 section triangles, C3D15 wedges over 140 mm,
CalculiX on every core) for the prismatic leg and the tapering one, and prints for each the wall time of meshing
and of ccx, the mesh's size, and the mid-segment plane's in-plane displacement against calfit-fe's plane strain on
the same section: under the same face pressures (the 3D solution's departure from plane strain, plus
discretization) and under the engine's own Laplace law, RMS and largest difference in % of max |u|. Then renders
one case at the default size (384 x 384 pixels of 0.4 mm, oversampling 3, a 4 mm slice of 7 sub-planes, a turn,
a tilt and a 3 mm slide) and prints its solve and render times. --fine uses the accuracy mesh (2,000 triangles,
layers of 4 mm near the slice); --deformed Avril's deformed-contour law (a fixed point of several solves).
Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.phantom.kspace3d import (
    LegMotion,
    build_phantom,
    leg_mesh_3d,
    make_kspace_case,
    plane_strain_difference,
    solve_leg3d,
)
from orchestrator.phantom.kspace3d.case import FINE_LAYERING  # noqa: E402
from orchestrator.phantom.kspace3d.mechanics3d import (
    DEFAULT_SECTION_ELEMENTS,
    FINE_SECTION_ELEMENTS,
    Layering,
)

THETA_KPA = (5.0, 13.0, 85.0, 65.0)
TENSION = 0.15
MOTION = LegMotion(turn_deg=-1.9, tilt_deg=0.5, tilt_axis_deg=100.0, shift_mm=(0.5, -1.0), slide_mm=3.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fine", action="store_true", help="the accuracy mesh")
    parser.add_argument("--deformed", action="store_true", help="the deformed-contour garment law")
    parser.add_argument("--no-case", action="store_true", help="skip rendering the case")
    args = parser.parse_args()
    law = "deformed" if args.deformed else "unloaded"
    phantom = build_phantom()
    layering = FINE_LAYERING if args.fine else Layering()
    elements = FINE_SECTION_ELEMENTS if args.fine else DEFAULT_SECTION_ELEMENTS
    print(f"3D leg, garment law {law}, theta {THETA_KPA} kPa, T {TENSION} N/mm")
    for name, leg in (("prismatic", phantom.leg.prismatic()), ("tapering", phantom.leg)):
        start = time.perf_counter()
        mesh = leg_mesh_3d(leg, phantom.scanner.extent_mm, focus_mm=[70.0], band_mm=6.0, layering=layering,
                           n_elements=elements)
        meshed = time.perf_counter() - start
        solution = solve_leg3d(mesh, THETA_KPA, TENSION, garment_law=law)
        check = plane_strain_difference(solution)
        runs = ", ".join(f"{r.wall_s:.1f} s ({r.increments} increments, {r.iterations} iterations)"
                         for r in solution.runs)
        print(f"{name:9s}: {len(mesh.section.elements)} triangles x {mesh.layers} layers = {len(mesh.elements)} C3D15, "
              f"{len(mesh.nodes)} nodes; meshing {meshed:.1f} s, ccx {runs}")
        for key, what in (("same_load", "same face loads"), ("engine_laplace", "engine's Laplace law")):
            c = check[key]
            print(f"           3D vs plane strain ({what}): RMS {100 * c['rms_over_max_u']:.3f} %, largest "
                  f"{100 * c['max_over_max_u']:.3f} % of max |u| = {c['max_u_mm']:.3f} mm")
        print(f"           largest uz in the mid plane {check['max_uz_mm_in_plane']:.4f} mm")
    if args.no_case:
        return
    with tempfile.TemporaryDirectory(prefix="kspace3d-bench-") as scratch:
        start = time.perf_counter()
        case, truth = make_kspace_case(Path(scratch) / "case", theta_kPa=THETA_KPA, tension_N_per_mm=TENSION,
                                       motion=MOTION, garment_law=law, fine=args.fine)
        import json

        timing = json.loads((truth / "truth.json").read_text())["timing_s"]
        print(f"case 384 x 384 at 0.4 mm (oversampling 3, 7 sub-planes): {time.perf_counter() - start:.1f} s in all, "
              f"solve {timing['solve']:.1f} s, render of both images {timing['render']:.1f} s")


if __name__ == "__main__":
    main()
