"""Small linear algebra that several stages share."""

from __future__ import annotations

import numpy as np


def symmetric_roots(covariance: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(C^-1/2, C^1/2), the symmetric roots of a covariance, so that a whitened residual r_i stays attached to
    measurement i; ValueError naming `what` when C is not positive definite."""
    values, vectors = np.linalg.eigh(covariance)
    if values[0] <= 0:
        raise ValueError(f"{what} is not positive definite")
    return (vectors / np.sqrt(values)) @ vectors.T, (vectors * np.sqrt(values)) @ vectors.T
