"""The leg decks that calfit-fe and CalculiX both run, beyond the plain leg slice: the slice under a garment pressure
that varies around the leg (a follower load whose tangent is unsymmetric) and the leg under the explicit garment
band with friction (penalty contact in both codes). Written as one self-contained text each (the mesh inline), so
that tests/support/ccx_reference/ can store what CalculiX ran and benchmarks/engine.py times the same decks."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from engine_run import node_to_surface

from orchestrator.engine.decks import MESH_INCLUDE_NAME, leg_garment_deck
from orchestrator.meshing import DEFAULT_MATERIALS, leg_slice_deck
from orchestrator.meshing.mesh import FACE_CORNERS


def nonuniform_follower_text(mesh, increments: int) -> str:
    """The leg slice `mesh` with a garment pressure that varies around the leg, p(theta) = p0 (1 + 0.5 cos theta +
    0.2 sin 2 theta) about the skin's centre (a garment's tension harmonics), ramped in `increments` increments at
    most (*STATIC 1/n, 1, 1e-5, 1/n)."""
    with tempfile.TemporaryDirectory() as folder:
        deck = Path(folder) / "leg.inp"
        leg_slice_deck(deck, mesh=mesh, include_mesh=False, static=(1.0 / increments, 1.0, 1e-5, 1.0 / increments))
        text = deck.read_text()
    centre = mesh.nodes[mesh.skin_loop].mean(axis=0)
    lines, in_dload = [], False
    for line in text.splitlines():
        if line.upper().startswith("*"):
            in_dload = line.upper().startswith("*DLOAD")
        elif in_dload and line.strip():
            element, face, value = (field.strip() for field in line.split(","))
            a, b = FACE_CORNERS[int(face.upper().removeprefix("P")) - 1]
            corners = mesh.elements[int(element) - 1]
            x, y = 0.5 * (mesh.nodes[corners[a]] + mesh.nodes[corners[b]]) - centre
            theta = np.arctan2(y, x)
            line = f"{element}, {face}, {float(value) * (1 + 0.5 * np.cos(theta) + 0.2 * np.sin(2 * theta)):.8g}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def garment_text(leg, band, friction_mu: float, **deck_options) -> str:
    """The leg `leg` under the explicit garment band `band` (orchestrator.meshing.garment_band) put on as
    templates/leg_garment.inp.j2 does, with Coulomb friction friction_mu and the deck's default penalty (other
    options of orchestrator.engine.decks.leg_garment_deck, e.g. release_static, in deck_options); the mesh inline, and the
    displacements of every node, leg and band, printed at the end (*NODE PRINT) for CalculiX, whose NALL, the leg
    mesh's node set, leaves the band out."""
    text = leg_garment_deck(DEFAULT_MATERIALS, band, leg, friction_mu=friction_mu, **deck_options)
    mesh_lines = band.include_text(leg)
    include = next(line for line in text.splitlines() if line.upper().startswith("*INCLUDE") and MESH_INCLUDE_NAME in line)
    text = text.replace(include, mesh_lines.rstrip("\n") + "\n*NSET, NSET=EVERY_NODE\nNALL, GARMENT_NODES", 1)
    head, last_step = text.rsplit("*STEP", 1)
    return head + "*STEP" + last_step.replace("*END STEP", "*NODE PRINT, NSET=EVERY_NODE\nU\n*END STEP")


# The garment with friction beside CalculiX: its node-to-surface contact (its face-to-face friction depends on its
# increments: tests/engine/test_engine_friction.py) and a release converged in its increments. Measured on the 2,000-element
# deck: calfit-fe's release in 5 (the deck's default), 10, 25, 50 and 100 increments is 1.1 %, 0.69 %, 0.13 %, 0.048 %
# and 0.008 % of max |u| from 200 increments; CalculiX's in 200 (485 s) is 0.25 % from calfit-fe's in 200 and 0.26 %
# from calfit-fe's in 50. With its own increments (0.2 down to 1e-3) it was 0.24 % from calfit-fe's converged release;
# capped at 0.02, 0.49 %; capped at 0.01 it stopped at t = 0.19 of the release.
GARMENT_FRICTION = 0.3   # textile on skin: 0.3 to 0.5 in the literature; the second paper gives no value
GARMENT_FRICTION_RELEASE = (0.005, 1.0, 1e-5, 0.005)


def garment_friction_text(leg, band, release_static=GARMENT_FRICTION_RELEASE) -> str:
    """garment_text with friction GARMENT_FRICTION, CalculiX's node-to-surface contact and the release in
    increments of release_static (initial, period, min, max)."""
    return node_to_surface(garment_text(leg, band, GARMENT_FRICTION, release_static=release_static, max_increments=400))
