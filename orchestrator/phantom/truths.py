"""Random true parameters for phantom cases: identification and diagnosis are tested on truths that are not the fits'
start (Avril et al. Table 2 central values), drawn within physiological ranges."""

from __future__ import annotations

import numpy as np

from ..forward import TABLE2_CENTRAL_KPA

# C10 fat, C10 muscle, Kv fat, Kv muscle (kPa): around the spread of Avril et al. Table 1
PHYSIOLOGICAL_KPA = ((2.0, 9.0), (6.0, 20.0), (50.0, 200.0), (35.0, 140.0))
MIN_OFFSET = 0.15   # every parameter at least this far (relative) from the fits' start


def random_truth(seed: int) -> np.ndarray:
    """Log-uniform in PHYSIOLOGICAL_KPA, each parameter at least MIN_OFFSET off TABLE2_CENTRAL_KPA (redrawn until)."""
    rng = np.random.default_rng(seed)
    start = np.array(TABLE2_CENTRAL_KPA)
    while True:
        truth = np.exp([rng.uniform(np.log(low), np.log(high)) for low, high in PHYSIOLOGICAL_KPA])
        if np.all(np.abs(truth / start - 1.0) > MIN_OFFSET):
            return truth
