"""Small linear algebra that several stages share."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

# The roots of the last few covariances, by their bytes: a command whitens the same measurements several times
# (the fit, its record, the discretization check's two meshes, the diagnosis), each an eigendecomposition of a
# (2N, 2N) matrix (about 1 s at 2,400 values on this machine), where one suffices. Read-only, so that no caller
# changes what another is handed.
ROOTS_KEPT = 2
_roots: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_roots_lock = threading.Lock()


def _key(covariance: np.ndarray) -> tuple:
    return covariance.shape, hashlib.blake2b(covariance.data, digest_size=20).hexdigest()


def symmetric_roots(covariance: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(C^-1/2, C^1/2), the symmetric roots of a covariance, so that a whitened residual r_i stays attached to
    measurement i; ValueError naming `what` when C is not positive definite. The same covariance again (bytes
    equal) is handed the same read-only roots, not decomposed again (`ROOTS_KEPT`)."""
    covariance = np.ascontiguousarray(covariance, dtype=float)
    key = _key(covariance)
    with _roots_lock:
        if key in _roots:
            _roots.move_to_end(key)
            return _roots[key]
    values, vectors = np.linalg.eigh(covariance)
    if values[0] <= 0:
        raise ValueError(f"{what} is not positive definite")
    roots = ((vectors / np.sqrt(values)) @ vectors.T, (vectors * np.sqrt(values)) @ vectors.T)
    for root in roots:
        root.setflags(write=False)
    with _roots_lock:
        _roots[key] = roots
        while len(_roots) > ROOTS_KEPT:
            _roots.popitem(last=False)
    return roots
