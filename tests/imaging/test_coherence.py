"""The texture coherence between the two slices (`imaging.coherence`): 1 for the same tissue moved, whatever the
noise; the share of the texture that stays where part of it is another height's."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from orchestrator.imaging.coherence import (
    SAME_TISSUE,
    coherence_sentence,
    texture_coherence,
)

SHAPE = (192, 192)
NOISE = 0.02


def texture(seed: int) -> np.ndarray:
    field = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(SHAPE), 1.5)
    return 0.5 + 0.1 * field / field.std()


def test_the_same_texture_coheres_at_one_and_a_partly_new_one_by_its_share():
    rng = np.random.default_rng(7)
    tissue, other = texture(1), texture(2)
    mask = np.ones(SHAPE, bool)
    noisy = lambda image: image + NOISE * rng.standard_normal(SHAPE)
    same = texture_coherence(noisy(tissue), noisy(tissue), mask, (NOISE, NOISE), "fat")
    assert abs(same.coherence - 1.0) < 0.02, same
    # 70 % of the texture's amplitude kept, 30 % another's: rho = 0.7 / sqrt(0.7^2 + 0.3^2)
    mixed = 0.5 + 0.7 * (tissue - 0.5) + 0.3 * (other - 0.5)
    part = texture_coherence(noisy(tissue), noisy(mixed), mask, (NOISE, NOISE), "fat")
    assert abs(part.coherence - 0.7 / np.hypot(0.7, 0.3)) < 0.03, part
    assert coherence_sentence([same]) is None
    assert part.coherence < SAME_TISSUE and "volumes" in coherence_sentence([same, part])


def test_too_few_patches_in_the_tissue_give_no_coherence():
    mask = np.zeros(SHAPE, bool)
    mask[:20, :20] = True
    assert texture_coherence(texture(1), texture(1), mask, (NOISE, NOISE), "muscle") is None
