"""The second paper's model diagnosed from its images: Bouten and Drapier's Table 1 Mooney-Rivlin tissues,
incompressible on u/p elements (CPE6H), under the explicit garment band with Coulomb friction (mu = 0.3), fitted
with the same model (`phantom.truths.SECOND_PAPER_FIT_TABLES`) from the default start (half of Avril et al.'s
Table 2 C10, 2 to 6 times the truth).

Each case is made by the engine on its own 8,000-element mesh of the phantom's shapes (the fit meshes calfit's
segmentation of I0 with 2,000), with a rigid scanner motion and image noise; the case folder holds the two images
and case.toml only. Measured by DIC, identified by Levenberg-Marquardt on the engine's sensitivities (carried along
the put-on's path through friction), then diagnosed:

- a hidden drainage of the muscle, a hidden prestretch profile of the band (band_profile, the band's tension
  varying around the leg) and hidden compartments are each ranked first, significant, and refitted to <= 1.2 x the
  noise floor;
- a control (nothing hidden) shows nothing significant;
- a swelling of the fat in one sector (outside the catalog) is declared unexplained, and located in its sector.

Every case is slow (a run of the band with friction on the 3,990 elements the discretization check asks for takes
30-40 s, the diagnosis's probe of every group's stiffness about 3 minutes beside other jobs): `make test-slow`.

Measured (one sock, this machine, beside other jobs; every case meshed again by the discretization check to about
4,000 elements, the skin's uncertainty through the band, `SHAPE` columns, settled in 1-3 passes). Stop 47, on the
DIC of 08613ff (noise share exact, noise moments by the Rician share), the five beside one another and a benchmark:
- drainage **passes** (1 h 31 min): baseline 8,830 x the floor, drainage first (statistic 365,625, out_of_plane
  356,569: tied by the score, their refits deciding), refitted to 1.08 x its own floor (out_of_plane's refit 201 x),
  dv -0.0501 (truth -0.05);
- band_profile **passes** (52 min): baseline 222 x with the fat on its upper bounds (30 kPa), band_profile first
  (statistic 7,071; heterogeneity 5,113), refitted to 0.92 x its own floor, band_a1 0.0498, band_b1 -0.0299 (truth
  0.05, -0.03);
- compartments **pass** (66 min): baseline 41.6 x, compartments first (statistic 2,722; heterogeneity 2,345),
  refitted to 0.95 x its own floor, dC10 of compartments 5, 6, 7 -0.576, 1.907, -0.617 (truth -0.6, 2.0, -0.6);
- the control **passes** (10 min): 0.90 x the floor, nothing significant (bone_motion p 0.051 the lowest);
- the swelling **passes** (56 min): baseline 94.4 x, no catalog effect explains it (out_of_plane's refit 76.4 x),
  the residual largest in the fat, sector 240-270 deg, 0-5 mm under the skin (the swelling's sector 210-300 deg);
  the local change there refitted to 92.0 x, no explanation either.
Stops 42-43 (the engine before UMFPACK's symmetric strategy, the DIC before) gave the same ranks and verdicts
(drainage 9,194 x -> 1.08 x, 2 h 6 min).
In every case with a catalog effect the local change's refit was left out (`diagnose.local_refit_unneeded`).
"""

from __future__ import annotations

import re
from functools import partial

import pytest
from hidden_physics import (
    OEDEMA_SECTOR_DEG,
    assert_found_or_nothing,
    identified_and_diagnosed,
    oedema,
)

from orchestrator.core.frame import RigidMotion
from orchestrator.model.regions import SECTORS
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import (
    SECOND_PAPER_FIT_TABLES,
    SECOND_PAPER_KPA,
    SECOND_PAPER_TISSUES,
)

SCANNER_MOTION = RigidMotion(-0.8, (-0.5, 0.3), (75.0, 75.0))
SECTOR_DEG = 360.0 / SECTORS
HIDDEN = {
    "drainage": {"dv_muscle": -0.05},
    "band_profile": {"band_a1": 0.05, "band_b1": -0.03},
    "compartments": {"dC10_COMPARTMENT5": -0.6, "dC10_COMPARTMENT6": 2.0, "dC10_COMPARTMENT7": -0.6},
}
CASES = [*HIDDEN, "control", "oedema"]
# Smaller than the Laplace cases' 0.15: the band barely compresses the incompressible muscle, and 0.15 in one sector
# of fat left the loaded leg 1.0 % larger than the unloaded one, which calfit refuses as swapped images.
OEDEMA_DV = 0.05


@pytest.fixture(scope="module", params=[pytest.param(name, marks=pytest.mark.slow) for name in CASES])
def second_paper(request, tmp_path_factory):
    name = request.param
    folder = tmp_path_factory.mktemp(f"second-paper-{name}")
    case, _ = make_phantom_case(folder / "case", theta_kPa=list(SECOND_PAPER_KPA.values()), rigid=SCANNER_MOTION,
                                points_spacing_mm=None, garment="explicit", friction_mu=0.3, hybrid=True,
                                tissues=SECOND_PAPER_TISSUES, effects={name: HIDDEN[name]} if name in HIDDEN else None,
                                labels="compartments" if name == "compartments" else "segmented",
                                edit_deck=partial(oedema, dv=OEDEMA_DV) if name == "oedema" else None)
    return name, identified_and_diagnosed(case, folder / "run", name, SECOND_PAPER_FIT_TABLES)


def test_the_second_paper_s_diagnosis(second_paper):
    name, diagnosis = second_paper
    if name != "oedema":
        assert_found_or_nothing(name, diagnosis)
        return
    assert diagnosis["lack_of_fit_p"] < 1e-6
    assert not diagnosis["explained"] and "no catalog effect explains the residual" in diagnosis["verdict"]
    maps = diagnosis["maps"]
    low, high = (float(v) for v in re.search(r"sector (\d+)-(\d+) deg", maps["worst_region"]).groups())
    assert OEDEMA_SECTOR_DEG[0] - SECTOR_DEG <= low < high <= OEDEMA_SECTOR_DEG[1] + SECTOR_DEG, maps["worst_region"]
