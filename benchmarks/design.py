"""Wall time of `calfit design` (orchestrator/design/) for one slice and for a 12-slice volume, on this machine.

    .venv/bin/python benchmarks/design.py [--out DIR] [--slices 12] [--draws 20] [--workers 2] [--study STUDY_DIR]

The legs are phantoms with known truth, identified (not timed): one calf slice (truth on 2,000 CPE6, points every
6 mm, identified on 400 CPE6, 20 noise Monte-Carlo draws), and a stack of --slices such slices whose girth follows a
calf from the ankle (B) through its widest (C) to below the knee (D), the truth stiffer towards the knee, laid out
as a volume study (slices.json naming B, B1, C, D; the stack is built from slice phantoms, as
tests/design/test_design_volume.py builds its four, so that the design's time is measured apart from a volume's
slicing). --study times a volume study `calfit study` made instead. The slice is designed for RAL-GZ 387/1
class II at B and at least 15 mmHg at the deep veins, the volume for class II at B with the graduation and at
least 15 mmHg at the deep veins at C. Prints, for each, the wall time, the engine runs, the tension and each
target's value and probability. DIR (default benchmarks-design/ in the current folder) keeps the identified
phantoms, so a second run times the design alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.core.files import write_json
from orchestrator.design.report import target_lines
from orchestrator.design.stage import run_design
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.geometry import CalfGeometry, CalfShape
from orchestrator.run.stages import run_identify, run_montecarlo

SLICE_TARGETS = """[design]
tension_range_N_per_mm = [0.05, 0.6]
slice_height = "B"
[[target]]
height = "B"
class = "RAL II"
[[target]]
landmark = "deep_veins"
min_mmHg = 15
"""
VOLUME_TARGETS = """[design]
tension_range_N_per_mm = [0.05, 0.6]
[[target]]
height = "B"
class = "RAL II"
[[target]]
landmark = "deep_veins"
height = "C"
min_mmHg = 15
"""
# the leg along its height (mm): the outline's scale against the standard calf and the truth's C10s (kPa)
PROFILE_HEIGHTS = (210.0, 240.0, 290.0, 330.0)
PROFILE_SCALE = (0.80, 0.88, 1.00, 0.93)
PROFILE_C10_FAT = (3.2, 3.4, 3.6, 3.9)
PROFILE_C10_MUSCLE = (11.0, 11.8, 12.4, 13.2)


def identified_slice(root: Path, name: str, scale: float, theta, draws: int, workers: int) -> Path:
    run = root / "cases" / name
    if (run / "montecarlo.json").is_file():
        return run
    shape = dataclasses.replace(CalfShape(), half_width_mm=58.0 * scale, half_depth_mm=52.0 * scale)
    case, _ = make_phantom_case(root / "phantoms" / name, root / "phantoms" / f"{name}.truth", theta_kPa=theta,
                                n_elements=2000, phantom=CalfPhantom(geometry=CalfGeometry(shape)), overwrite=True)
    run_identify(case, run, method="lm", objective="displacement", n_elements=400, order=2, progress=False)
    run_montecarlo(run, draws=draws, workers=workers, progress=False)
    return run


def phantom_stack(root: Path, n: int, draws: int, workers: int) -> Path:
    heights = np.linspace(PROFILE_HEIGHTS[0], PROFILE_HEIGHTS[-1], n)
    entries = []
    for height in heights:
        scale = float(np.interp(height, PROFILE_HEIGHTS, PROFILE_SCALE))
        theta = (float(np.interp(height, PROFILE_HEIGHTS, PROFILE_C10_FAT)),
                 float(np.interp(height, PROFILE_HEIGHTS, PROFILE_C10_MUSCLE)), 92.0, 74.0)
        name = f"slice-{height:.0f}mm"
        identified_slice(root, name, scale, theta, draws, workers)
        entries.append({"folder": str(root / "slices" / name), "height_mm": float(height)})
    named = {label: float(heights[np.argmin(np.abs(heights - h))]) for label, h in zip(("B", "B1", "C", "D"),
                                                                                        PROFILE_HEIGHTS)}
    write_json(root / "slices.json", {"slices": entries, "compression_heights_mm": named})
    return root


def timed(label: str, source: Path, text: str, out: Path, draws: int, workers: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    target = out / "TARGET.toml"
    target.write_text(text)
    began = time.perf_counter()
    result = run_design(source, target, out / "design", workers=workers, draws=draws)
    wall = time.perf_counter() - began
    tension = result["tension_N_per_mm"]
    shown = f"{tension:.4f}" if isinstance(tension, float) else ", ".join(
        f"{n or f'{h:.0f}'}: {t:.4f}" for n, h, t in zip(tension["height_names"], tension["heights_mm"],
                                                       tension["tension_N_per_mm"]))
    print(f"{label}: {wall:.1f} s wall, {result['engine_runs']} engine runs, status {result['status']}")
    print(f"  tension (N/mm): {shown}")
    for line in target_lines(result):
        print(f"  {line}")
    if result.get("graduation_probability") is not None:
        print(f"  graduation B > B1 > C > D, D <= 0.7 B: probability {result['graduation_probability']:.3f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks-design")
    parser.add_argument("--slices", type=int, default=12)
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--study", help="a volume study of calfit study to time instead of the phantom stack")
    args = parser.parse_args()
    out = Path(args.out)
    one = identified_slice(out / "one", "calf", 1.0, (3.6, 12.4, 92.0, 74.0), 20, args.workers)
    timed("one slice", one, SLICE_TARGETS, out / "one-design", args.draws, args.workers)
    stack = Path(args.study) if args.study else phantom_stack(out / "stack", args.slices, 20, args.workers)
    timed(f"{args.slices if not args.study else 'study'}-slice volume", stack, VOLUME_TARGETS, out / "stack-design",
          args.draws, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
