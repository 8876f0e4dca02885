"""Is an identification's error against the truth one of its noise Monte-Carlo's draws?

"Every truth inside its 95 % interval" is the wrong test over many intervals: over the 28 intervals of 7 cases,
intervals that hold exactly 95 % miss one three times out of four (1 - 0.95^28). The Monte-Carlo's refitted draws
give Cov(theta); the error must look like one of them: its Mahalanobis distance below chi^2 at 99.9 % with as many
degrees of freedom as parameters, and each parameter within 3.29 of its standard deviations (99.9 %, two-sided).
A biased fit still fails it.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

LEVEL = 0.999


def assert_error_is_a_draw(theta, truth, montecarlo: dict, names) -> None:
    draws = np.array(montecarlo["samples"])
    assert montecarlo["method"] == "noise" and montecarlo["failed"] == 0 and len(draws) >= 100
    covariance = np.cov(draws, rowvar=False)
    error = np.asarray(theta, float) - np.asarray(truth, float)
    distance = float(error @ np.linalg.solve(covariance, error))
    assert distance < stats.chi2.ppf(LEVEL, len(error)), f"Mahalanobis distance^2 {distance:.1f}"
    assert_each_error_within_its_spread(theta, truth, montecarlo, names)


def assert_each_error_within_its_spread(theta, truth, montecarlo: dict, names, only=None) -> None:
    """Each parameter's error within 3.29 standard deviations of the Monte-Carlo's draws (99.9 %, two-sided); `only`:
    the names to check (e.g. the identifiable ones, where a pair that acts through its sum has no spread of its
    own)."""
    draws = np.array(montecarlo["samples"])
    error = np.asarray(theta, float) - np.asarray(truth, float)
    for name, e, std in zip(names, error, draws.std(axis=0, ddof=1)):
        if only is None or name in only:
            assert abs(e) <= stats.norm.ppf(0.5 + LEVEL / 2) * std, f"{name}: error {e:.3f}, {abs(e) / std:.1f} std"
