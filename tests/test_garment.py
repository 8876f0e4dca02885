"""The explicit garment band of the second paper (Bouten and Drapier sec. 2.5, Fig. 2) against the
Laplace-law garment of the first (Avril et al. eq. 1, p = T / r), on the leg-like slice.

The band (orchestrator.meshing.garment_band) is inflated by an internal pressure with the contact
removed, then released onto the skin (templates/leg_garment.inp.j2). Its hoop force T is measured
by integrating the hoop Cauchy stress across its deformed thickness; the Laplace model of the same
leg is run with that T. Pressures are compared per skin face, as the face-mean pressure
(p_a + 4 p_m + p_b) / 6 (Simpson's rule on the quadratic face, corners a, b and mid-side m): the
engine's nodal values at T6 corners and mid-side nodes are each off the face mean in opposite
senses for the two outputs (contact_pressure about -10% / +5%, laplace_pressure the reverse),
while the face means and the displacements agree. Convexity is judged on the DEFORMED skin from
the signed curvature kappa = (x' y'' - y' x'') / |x'|^3 of the skin loop (Gaussian derivatives,
loop counter-clockwise in deck coordinates, so convex <=> kappa > 0).

Measured (leg slice, 1,000 T6 elements, band 0.5 mm, design T = 0.16 N/mm at stretch 1.15):
T = 0.1489 +- 0.0009 N/mm; all 82 skin faces convex; face-mean contact pressure / Laplace - 1 from
-0.020 to +0.015 (mean -0.008). Friction mu = 0.3: |delta p| / mean |p| over 994 tissue cells mean
0.043, max 0.30; band tension varies by 9.5% around the leg. The dented leg (concave stretch) does
not converge in the engine's inflation step yet (xfail).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from skimage.measure import points_in_poly

from engine_run import run_engine
from orchestrator.decks import GARMENT_STEPS, MESH_INCLUDE_NAME, leg_garment_deck, leg_laplace_deck
from orchestrator.meshing import (
    DEFAULT_MATERIALS,
    LegSliceGeometry,
    SpacingRules,
    band_constants_for_tension,
    band_hoop_tension,
    garment_band,
    leg_slice_geometry,
    leg_slice_mesh,
    mesh_curves,
    signed_areas,
)

N_ELEMENTS = 1000
CURVATURE_SIGMA_SAMPLES = 2.0
CONVEX_MARGIN_FACES = 2  # a face counts as convex when it and this many faces either side are
FRICTION_MU = 0.3


def dented_leg_mesh(n_elements: int, depth: float = 0.15, width_rad: float = 0.35):
    """The leg slice with a posterior dent: skin and fascia pulled towards the centre by the factor
    1 - depth exp(-(dtheta / width)^2) (about 7.6 mm deep, a concave stretch of about 14 mm)."""
    reference = leg_slice_geometry(0, spacing_mm=0.3)
    centre = np.array([75.0, 70.0])

    def dent(points):
        theta = np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0])
        offset = np.angle(np.exp(1j * (theta - np.pi / 2)))  # posterior = +y in the image frame
        return centre + (points - centre) * (1.0 - depth * np.exp(-((offset / width_rad) ** 2)))[:, None]

    geometry = LegSliceGeometry(dent(reference.skin), dent(reference.fascia), reference.bones)
    return mesh_curves(geometry.curves(), geometry.classify, n_elements, order=2, rules=SpacingRules(min_spacing=0.05))


def signed_curvature(loop_points: np.ndarray) -> np.ndarray:
    d1 = gaussian_filter1d(loop_points, CURVATURE_SIGMA_SAMPLES, axis=0, order=1, mode="wrap")
    d2 = gaussian_filter1d(loop_points, CURVATURE_SIGMA_SAMPLES, axis=0, order=2, mode="wrap")
    return (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.linalg.norm(d1, axis=1) ** 3


def face_means(loop_values: np.ndarray) -> np.ndarray:
    """Simpson face means of a nodal field on a T6 skin loop (corner, mid-side, corner, ...)."""
    corner, middle = loop_values[0::2], loop_values[1::2]
    return (corner + 4.0 * middle + np.roll(corner, -1)) / 6.0


class GarmentRun:
    """One garment run on one leg mesh, with its measured band tension and skin fields."""

    def __init__(self, leg, workdir, friction_mu=0.0):
        self.leg = leg
        self.band = garment_band(leg)
        workdir.mkdir(parents=True, exist_ok=True)
        (workdir / MESH_INCLUDE_NAME).write_text(self.band.include_text(leg))
        deck = leg_garment_deck(DEFAULT_MATERIALS, self.band, leg, friction_mu=friction_mu,
                                description=f"test_garment, mu = {friction_mu}")
        self.run = run_engine(deck, workdir)
        assert self.run.returncode == 0, self.run.stderr
        n_leg, m_leg = len(leg.nodes), len(leg.elements)
        self.released = self.run.vtu(GARMENT_STEPS["released"])
        u = np.asarray(self.released.point_data["displacement"])[:, :2]
        self.deformed = np.asarray(self.released.points)[:, :2] + u
        stress = np.asarray(self.released.cell_data["cauchy_stress"][0])
        self.tension = self.band.hoop_tension(self.deformed[n_leg:], stress[m_leg:])
        self.skin = self.deformed[leg.skin_loop]
        self.contact_pressure = np.asarray(self.released.point_data["contact_pressure"]).ravel()[leg.skin_loop]
        self.contact_shear = np.asarray(self.released.point_data["contact_shear"]).ravel()[leg.skin_loop]
        self.tissue_pressure = np.asarray(self.released.cell_data["pressure"][0]).ravel()[:m_leg]

    def inflated(self):
        """(deformed skin, deformed band inner contour) once inflated and let go (no contact yet)."""
        vtu = self.run.vtu(GARMENT_STEPS["inflated"])
        x = np.asarray(vtu.points)[:, :2] + np.asarray(vtu.point_data["displacement"])[:, :2]
        return x[self.leg.skin_loop], x[len(self.leg.nodes) + self.band.node_sets["GARMENT_INNER"]]


def laplace_run(leg, tension, workdir):
    workdir.mkdir(parents=True, exist_ok=True)
    leg.write_include(workdir / MESH_INCLUDE_NAME)
    run = run_engine(leg_laplace_deck(DEFAULT_MATERIALS, tension), workdir)
    assert run.returncode == 0, run.stderr
    return np.asarray(run.vtu(1).point_data["laplace_pressure"]).ravel()[leg.skin_loop]


@pytest.fixture(scope="module")
def leg():
    return leg_slice_mesh(N_ELEMENTS, order=2)


@pytest.fixture(scope="module")
def frictionless(leg, tmp_path_factory):
    return GarmentRun(leg, tmp_path_factory.mktemp("garment_mu0"))


def test_band_tension_formula_and_its_incompressible_limit():
    C10, D1 = band_constants_for_tension(0.16, 1.15, 0.5, poisson=0.4)
    assert band_hoop_tension(C10, D1, 1.15, 0.5) == pytest.approx(0.16, rel=1e-10)
    # Incompressible limit: T = 2 C10 t (l - l^-3).
    stretch, thickness = 1.3, 0.5
    assert band_hoop_tension(1.0, 1e-7, stretch, thickness) == pytest.approx(
        2.0 * thickness * (stretch - stretch**-3), rel=1e-5)
    assert band_hoop_tension(1.0, 1e-7, 1.0, thickness) == pytest.approx(0.0, abs=1e-9)


def test_band_mesh_is_a_closed_counter_clockwise_ring(leg):
    band = garment_band(leg)
    areas = signed_areas(band.nodes, band.elements)
    assert np.all(areas > 0)
    # Ring area = (inner perimeter + pi t) t, the inner contour being the skin scaled by 1/stretch.
    skin = leg.nodes[leg.skin_loop[::2]]
    perimeter = np.linalg.norm(np.roll(skin, -1, axis=0) - skin, axis=1).sum() / band.design_stretch
    assert areas.sum() == pytest.approx((perimeter + np.pi * band.thickness_mm) * band.thickness_mm, rel=2e-2)
    assert len(band.inner_faces) == len(leg.skin_faces)
    assert len(band.node_sets["GARMENT_PIN_X"]) == 2 and len(band.node_sets["GARMENT_PIN_Y"]) == 1


def test_inflated_band_clears_the_skin(frictionless):
    skin, band_inner = frictionless.inflated()
    assert np.all(points_in_poly(skin, band_inner))


def test_frictionless_garment_agrees_with_laplace_law_on_convex_skin(frictionless, leg, tmp_path):
    """Measured: T = 0.149 N/mm (design 0.16; the tissue yields), uniform within 1% around the
    leg; the whole skin is convex and face-mean contact pressures match T / r within 2.1%."""
    T = frictionless.tension
    assert T.std() < 0.02 * T.mean()  # frictionless: no tangential traction, T constant
    assert 0.8 * frictionless.band.design_tension_N_per_mm < T.mean() < frictionless.band.design_tension_N_per_mm
    laplace = laplace_run(leg, float(T.mean()), tmp_path / "laplace")
    kappa = signed_curvature(frictionless.skin)
    convex_node = kappa > 0.0
    convex_face = convex_node[0::2] & convex_node[1::2] & np.roll(convex_node[0::2], -1)
    for shift in range(1, CONVEX_MARGIN_FACES + 1):
        convex_face &= np.roll(convex_face, shift) & np.roll(convex_face, -shift)
    assert convex_face.mean() > 0.5
    contact, reference = face_means(frictionless.contact_pressure), face_means(laplace)
    relative = contact[convex_face] / reference[convex_face] - 1.0
    print(f"\nT = {T.mean():.4f} +- {T.std():.4f} N/mm; {convex_face.sum()} of {len(convex_face)} faces convex; "
          f"contact / Laplace - 1: mean {relative.mean():+.4f}, min {relative.min():+.4f}, max {relative.max():+.4f}")
    assert np.all(np.abs(relative) < 0.05)
    assert np.all(frictionless.contact_shear == 0.0)


@pytest.mark.slow
def test_band_bridges_a_concave_stretch(tmp_path):
    """The dented leg: the band lifts off the concave stretch (contact_pressure = 0) where the
    Laplace model, with r < 0 there, pulls the skin outwards (laplace_pressure < 0)."""
    leg = dented_leg_mesh(N_ELEMENTS)
    garment = GarmentRun(leg, tmp_path / "garment")
    laplace = laplace_run(leg, float(garment.tension.mean()), tmp_path / "laplace")
    kappa = signed_curvature(garment.skin)
    concave = kappa < 0.0
    arc = np.linalg.norm(np.roll(garment.skin, -1, axis=0) - garment.skin, axis=1)
    open_contact = garment.contact_pressure == 0.0
    print(f"\nconcave stretch {arc[concave].sum():.1f} mm ({concave.sum()} nodes); open contact "
          f"{arc[open_contact].sum():.1f} mm ({open_contact.sum()} nodes), {np.sum(open_contact & concave)} of them "
          f"concave; Laplace pressure on the concave stretch {laplace[concave].min():.3e} .. {laplace[concave].max():.3e}")
    assert concave.sum() >= 3
    assert np.sum(open_contact & concave) >= 0.5 * concave.sum()
    assert np.all(laplace[concave & open_contact] < 0.0)
    assert np.all(garment.contact_pressure[~open_contact] > 0.0)


@pytest.mark.slow
def test_friction_changes_the_tissue_pressure_map(frictionless, leg, tmp_path):
    """mu = 0.3: relative change of the tissue pressure -tr(sigma)/3 per cell, |delta p| / mean |p|."""
    rough = GarmentRun(leg, tmp_path / "garment_mu03", friction_mu=FRICTION_MU)
    reference = np.abs(frictionless.tissue_pressure).mean()
    change = np.abs(rough.tissue_pressure - frictionless.tissue_pressure) / reference
    tension_spread = (rough.tension.max() - rough.tension.min()) / rough.tension.mean()
    print(f"\nfriction mu = {FRICTION_MU}: |delta p| / mean |p| over {len(change)} tissue cells: mean {change.mean():.4f}, "
          f"max {change.max():.4f}; band tension spread {tension_spread:.3f}; max |shear| "
          f"{np.abs(rough.contact_shear).max():.3e} MPa")
    assert np.abs(rough.contact_shear).max() > 0.0
    assert 1e-3 < change.mean() < 0.5
    assert change.max() < 2.0
