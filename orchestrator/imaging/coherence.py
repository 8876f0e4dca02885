"""Does the loaded slice show the same tissue as the unloaded one? The coherence of their textures.

A slice is a few millimetres thick, and the leg may slide or tilt along its axis between the sessions: the loaded
slice then shows the tissue of another height, whose fine texture (fat septa, vessels, the fat in the muscle) is
not the unloaded slice's moved. DIC still matches what the two share, but its errors are then no longer those of
the images' noise: features cut at another height sit elsewhere, appear and vanish, and nothing in the error model
of a window (`windows`, `prefilter`) knows of it.

Measured here, after the match: I1 is sampled where the measured field and the bones' motion carry each pixel of
I0, and over square patches of one tissue the two images' spectra give the coherence

    rho(k) = Re sum I0^(k) conj(I1w^(k)) / sqrt((sum |I0^|^2 - N0) (sum |I1w^|^2 - N1))

in a band of spatial frequencies, N0 and N1 the images' white noise over the same patches (their estimated sigma;
a Hann window on each patch). Where the loaded slice shows the same tissue, moved, rho is 1 whatever the noise
(the other program's k-space control, the same slice in both sessions: 1.00 in the fat and the muscle at every
band up to 0.5 cycle per pixel); with the leg slid 3 mm along its axis, 0.86 in the fat at 0.08-0.15 cycle per
pixel and 0.96 in the muscle. How far apart the slices lie cannot be read from it: that depends on how fast the
tissue's structure changes with height, which one slice does not show (a volume does: `imaging.align3d` finds the
slide). The setup says so and the coherence (`measure`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATCH_PX = 32
BAND_CYCLES_PER_PX = (0.08, 0.15)   # about 7-12 px wavelengths: the fat's septa and the muscle's streaks
MIN_PATCHES = 4
SAME_TISSUE = 0.95                   # below it the loaded slice is said not to show the unloaded slice's tissue


@dataclass(frozen=True)
class Coherence:
    """One tissue's texture coherence between I0 and the warped I1, over `patches` patches."""

    tissue: str
    coherence: float
    patches: int
    signal_over_noise: float   # the texture's power in the band over the noise's, in I0

    def as_dict(self) -> dict:
        return {"tissue": self.tissue, "coherence": float(self.coherence), "patches": int(self.patches),
                "signal_over_noise": float(self.signal_over_noise)}


def texture_coherence(reference: np.ndarray, warped: np.ndarray, mask: np.ndarray, noise_sigma: tuple[float, float],
                      tissue: str, band=BAND_CYCLES_PER_PX) -> Coherence | None:
    """rho of the module text over the PATCH_PX patches (half overlapping) whose central half lies in `mask`; None
    with fewer than MIN_PATCHES or no texture above the noise in the band."""
    reference, warped = np.asarray(reference, float), np.asarray(warped, float)
    taper = np.outer(np.hanning(PATCH_PX), np.hanning(PATCH_PX))
    frequency = np.hypot(*np.meshgrid(np.fft.fftfreq(PATCH_PX), np.fft.fftfreq(PATCH_PX), indexing="ij"))
    selected = (frequency >= band[0]) & (frequency < band[1])
    half, quarter = PATCH_PX // 2, PATCH_PX // 4
    cross = power0 = power1 = 0.0
    patches = 0
    for row in range(half, reference.shape[0] - half + 1, half):
        for col in range(half, reference.shape[1] - half + 1, half):
            if not mask[row - quarter:row + quarter, col - quarter:col + quarter].all():
                continue
            a = reference[row - half:row + half, col - half:col + half]
            b = warped[row - half:row + half, col - half:col + half]
            if not np.all(np.isfinite(b)):
                continue
            fa, fb = (np.fft.fft2((p - p.mean()) * taper)[selected] for p in (a, b))
            cross += float(np.real(np.sum(fa * np.conj(fb))))
            power0 += float(np.sum(np.abs(fa) ** 2))
            power1 += float(np.sum(np.abs(fb) ** 2))
            patches += 1
    if patches < MIN_PATCHES:
        return None
    per_patch = float(np.sum(taper ** 2)) * selected.sum()
    noise0, noise1 = (patches * per_patch * float(s) ** 2 for s in noise_sigma)
    if power0 <= noise0 or power1 <= noise1:
        return None
    return Coherence(tissue, cross / np.sqrt((power0 - noise0) * (power1 - noise1)), patches,
                     power0 / noise0 - 1.0)


def coherence_sentence(values: list[Coherence]) -> str | None:
    """A warning when some tissue's texture does not cohere (under SAME_TISSUE), None otherwise."""
    low = [c for c in values if c.coherence < SAME_TISSUE]
    if not low:
        return None
    measured = ", ".join(f"{c.coherence:.2f} in the {c.tissue}" for c in values)
    return (f"the loaded slice does not show the unloaded slice's tissue moved: their fine texture coheres {measured} "
            f"(1.00 for the same tissue, the noise taken out; below {SAME_TISSUE:g} here), as when the slices lie "
            "millimetres apart along the leg (the leg slid or tilted between the sessions); the error model does not "
            "cover that, so the misfit and the intervals are not to be trusted; how far apart the slices lie two "
            "slices cannot tell: measure both sessions as volumes (calfit study) to find the slide")
