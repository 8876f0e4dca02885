"""Laplace's law beside the FE model: what the trade's formula predicts for a garment, and the garment it would
have chosen.

The hosiery trade designs with Laplace's law on the skin, P = T / r (P = T N / (C W) with N layers of a fabric of
width W on a girth C): on the unloaded leg's skin, its mean 2 pi T / C, its local value T kappa on the skin's own
curvature (smoothed as `slices.skin_pressures` smooths the FE's). It sees no tissue, so at a vein it can only say
the skin's pressure arrives whole: its prediction at every landmark is the skin's mean pressure. `evaluate` is
a `slices.evaluate` without the engine (linear in T, so its derivatives are exact); the Laplace-only garment is
`solve.levenberg_marquardt` run on it, and what that garment really gives is then the FE model's at that garment.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .slices import (
    PROFILE_NAMES,
    REGION_NAMES,
    DesignSlice,
    Response,
    harmonic,
    skin_pressures,
)


def evaluate(piece: DesignSlice, tension: float, profile: Sequence[float], theta=None) -> Response:
    """Laplace's law's pressures for the garment on the unloaded skin (theta is not used: the law has no tissue)."""
    points = piece.mesh.nodes[piece.skin_nodes]
    factor = piece.factor(profile)
    skin = skin_pressures(points, tension * factor, piece)
    columns = [skin_pressures(points, factor, piece)]
    columns += [skin_pressures(points, tension * harmonic(piece, name), piece)
                for name in PROFILE_NAMES[:len(profile)]]
    d_mean = np.array([c["mean"] for c in columns])
    d_regions = {name: np.array([c["local"][skin["argmax"][name]] for c in columns]) for name in REGION_NAMES}
    landmarks = {name: skin["mean"] for name in piece.landmarks}
    return Response(landmarks, skin["mean"], skin["regions"], {name: d_mean.copy() for name in piece.landmarks},
                    d_mean, d_regions, skin["perimeter"], sensitivity="laplace")
