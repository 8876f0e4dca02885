"""Memory and time of `calfit measure` (read, segment, align, find compartments, mesh, DIC) as the matrix grows:
the phantom calf over the same 151 mm field of view at 420x420, 1024x1024 and 2048x2048 pixels. Each size
runs in its own process, whose peak resident memory (VmHWM of /proc/self/status: getrusage's ru_maxrss
would carry the parent's peak over the exec) is printed with the working pixel (`imaging.resolution`), the
wall time, the number of DIC windows kept and the bytes of one image (float64), so that the memory can be
read as a multiple of the image. Prints figures, asserts nothing.

    .venv/bin/python benchmarks/large_slice.py [--sizes 420 1024 2048]

The loaded image is the phantom under the analytic bone-clamped compression (no engine run), rendered
without supersampling at the larger sizes (the pixels are already finer than the texture).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FIELD_OF_VIEW_MM = 151.2

CHILD = """
import json, re, sys, time
from pathlib import Path
from orchestrator.run.stages import run_measure
began = time.perf_counter()
summary = run_measure(sys.argv[1], sys.argv[2])
peak_kib = int(re.search(r"VmHWM:\s+(\d+) kB", Path("/proc/self/status").read_text()).group(1))
print(json.dumps({"seconds": time.perf_counter() - began, "windows": summary["kept"], "peak_mib": peak_kib / 1024.0,
                  "working_pixel_mm": summary["window_mm"] / summary["window_px"]}))
"""


def write(folder: Path, size: int) -> Path:
    from orchestrator.phantom import CalfPhantom, write_case

    pixel = FIELD_OF_VIEW_MM / size
    phantom = CalfPhantom(image_shape=(size, size), pixel_size_mm=(pixel, pixel), supersampling=3 if size <= 420 else 1)
    case, _ = write_case(folder / f"case-{size}", phantom, labels=None)
    return case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[420, 1024, 2048])
    args = parser.parse_args()
    print(f"{'matrix':>10} {'pixel mm':>9} {'render s':>9} {'worked at':>10} {'measure s':>10} {'windows':>8} {'image MiB':>10} "
          f"{'peak MiB':>9} {'peak / image':>13}")
    with tempfile.TemporaryDirectory(prefix="calfit-large-") as scratch:
        for size in args.sizes:
            began = time.perf_counter()
            case = write(Path(scratch), size)
            rendered = time.perf_counter() - began
            done = subprocess.run([sys.executable, "-c", CHILD, str(case), str(Path(scratch) / f"run-{size}")],
                                  capture_output=True, text=True, check=True)
            figures = json.loads(done.stdout.strip().splitlines()[-1])
            image_mib = size * size * 8 / 2 ** 20
            print(f"{size:>5}x{size:<4} {FIELD_OF_VIEW_MM / size:>9.4f} {rendered:>9.1f} "
                  f"{figures['working_pixel_mm']:>10.4f} {figures['seconds']:>10.1f} "
                  f"{figures['windows']!s:>8} {image_mib:>10.1f} {figures['peak_mib']:>9.0f} "
                  f"{figures['peak_mib'] / image_mib:>13.0f}", flush=True)


if __name__ == "__main__":
    main()
