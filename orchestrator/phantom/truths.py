"""True parameters for phantom cases: random ones, since identification and diagnosis are tested on truths that are
not the fits' start (Avril et al. Table 2 central values), drawn within physiological ranges; and the second paper's
model (Bouten and Drapier Table 1), with the case.toml tables that fit it back."""

from __future__ import annotations

import numpy as np

from ..core.materials import TissueLaw
from ..model.forward import TABLE2_CENTRAL_KPA

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


# Bouten and Drapier Table 1 (kPa): adipose and gastrocnemius Mooney-Rivlin, incompressible, the fat's C20 -0.04 kPa
SECOND_PAPER_KPA = {"C10_fat": 1.4, "C10_muscle": 0.9, "C01_fat": 1.0, "C01_muscle": 0.6}
SECOND_PAPER_TISSUES = {"fat": TissueLaw("mooney_rivlin", terms=3, incompressible=True, fixed={"C20": -0.04}),
                        "muscle": TissueLaw("mooney_rivlin", incompressible=True)}
# case.toml tables of the second paper's model as it is fitted: u/p elements, the band with friction 0.3, the muscle's
# C01 fixed at its Table 1 value (in plane strain the fat's C10 and C01 act only through their sum)
SECOND_PAPER_FIT_TABLES = """
[model]
element = "CPE6H"
garment = "explicit"
friction = 0.3
[model.fat]
law = "mooney_rivlin"
terms = 3
incompressible = true
fixed = { C20 = -0.04 }
[model.muscle]
law = "mooney_rivlin"
incompressible = true
fixed = { C01 = 0.6 }
"""
