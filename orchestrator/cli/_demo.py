"""The built-in demonstration: a leg-like calf slice (fat and muscle, clamped tibia
and fibula) under a garment of tension T, with the Laplace law p = T / r on the skin
(Avril et al. eq. 1) and the compressible neo-Hookean law of Avril et al. (eq. 2) at the
central values of their Table 2. It writes the deck, solves it with calfit-fe and prints
the result summary and the pressures transmitted to the tissues.

    calfit demo [--out DIR] [--elements N] [--order 1|2] [--tension T]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..meshing import leg_slice_deck
from ..results import EngineResults
from ..runner import run_engine
from ._solve import describe

HELP = "solve the built-in leg slice end to end and print the result"

# Avril et al. (2010), Table 2, central values, in MPa: (C10, Kv).
TABLE2_CENTRAL = {"FAT": ("AVRIL", (4.5e-3, 106e-3)), "MUSCLE": ("AVRIL", (11.2e-3, 69.5e-3))}
KPA_PER_MPA = 1e3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo-out", help="folder for the deck and results (default: demo-out)")
    parser.add_argument("--elements", type=int, default=5500, help="number of elements (default 5500, as paper 2)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=2, help="1: CPE3, 2: CPE6 (default)")
    parser.add_argument(
        "--tension", type=float, default=0.16, help="garment tension in N/mm (default 0.16, about 20 mmHg)"
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    deck = out / "leg_slice.inp"
    print(f"writing {deck} ({args.elements} elements, garment tension {args.tension} N/mm)", file=sys.stderr)
    leg_slice_deck(deck, n_elements=args.elements, order=args.order, materials=TABLE2_CENTRAL,
                   laplace_tension=args.tension)
    outcome = run_engine(deck, out / "results", threads=None, echo=True)
    results = EngineResults(outcome.outdir)
    print(describe(results))
    mesh = results.mesh()
    pressure = np.asarray(mesh.cell_data["pressure"][0]).ravel() * KPA_PER_MPA
    material = np.asarray(mesh.cell_data["material_id"][0]).ravel().astype(int)
    skin = np.asarray(mesh.point_data["laplace_pressure"]).ravel() * KPA_PER_MPA
    for index, name in enumerate(TABLE2_CENTRAL, start=1):
        p = pressure[material == index]
        print(f"{name.lower():<11} hydrostatic pressure {p.min():.2f} .. {p.max():.2f} kPa (mean {p.mean():.2f})")
    loaded = skin[skin != 0.0]
    print(f"garment     Laplace pressure on the skin {loaded.min():.2f} .. {loaded.max():.2f} kPa")
    print(f"open {outcome.outdir / 'step-1.vtu'} in ParaView to see the fields")
    return 0 if outcome.converged else 3
