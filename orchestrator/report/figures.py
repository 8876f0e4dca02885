"""Figures a user reads: matplotlib, axes in mm (image frame of I0: x right, y down), colour bars with values
and units, perceptually uniform colour maps. Written as PNG with the Agg backend (no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.digits import with_uncertainty
from ..engine.results import MMHG_PER_KPA

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend is chosen before pyplot is imported)

DPI = 150


def _image_axes(ax, image: np.ndarray, pixel_size_mm) -> None:
    dy, dx = pixel_size_mm
    height, width = image.shape
    low, high = np.percentile(image, [1, 99.5])
    ax.imshow(image, cmap="gray", vmin=low, vmax=high, extent=(0, width * dx, height * dy, 0), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")


def dic_vectors_figure(path: Path, image: np.ndarray, pixel_size_mm, table, summary: dict) -> Path:
    """The measured displacements drawn on the unloaded image: kept windows as arrows coloured by magnitude
    (mm, with a colour bar), rejected windows as crosses, a scale arrow, the counts in the legend."""
    kept = table.kept
    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    _image_axes(ax, image, pixel_size_mm)
    position, displacement = table.position_mm, table.displacement_mm
    magnitude = np.hypot(displacement[kept, 0], displacement[kept, 1])
    largest = float(np.max(magnitude)) if magnitude.size else 1.0
    spacing = summary.get("step_px", 16) * min(pixel_size_mm)
    scale = largest / (1.5 * spacing) if largest > 0 else 1.0   # the largest arrow spans 1.5 window steps
    arrows = ax.quiver(position[kept, 0], position[kept, 1], displacement[kept, 0], displacement[kept, 1], magnitude,
                       cmap="viridis", angles="xy", scale_units="xy", scale=scale, width=0.003)
    figure.colorbar(arrows, ax=ax, shrink=0.8, label="displacement relative to the bones (mm)")
    rejected = ~kept & np.all(np.isfinite(position), axis=1)
    if rejected.any():
        ax.plot(position[rejected, 0], position[rejected, 1], "x", color="tab:red", markersize=4,
                label=f"rejected windows ({int(rejected.sum())})")
    reference = float(f"{largest:.1g}") if largest > 0 else 1.0
    ax.quiverkey(arrows, 0.80, 1.02, reference, f"{reference:g} mm", labelpos="E", coordinates="axes")
    ax.plot([], [], marker=r"$\rightarrow$", linestyle="none", color="tab:green",
            label=f"kept windows ({int(kept.sum())} of {len(kept)})")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title(f"DIC, {summary['window_px']} px windows ({summary['window_px'] * pixel_size_mm[1]:.1f} mm), "
                 f"arrows x{1 / scale:.0f}", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def compartments_figure(path: Path, image: np.ndarray, pixel_size_mm, compartments) -> Path:
    """The muscle compartments found in I0 (`imaging.compartments`), each tinted and named at its centroid,
    over the septa they rest on (red), for the user to check before trusting the `compartments` effect."""
    from ..imaging.compartments import FIRST_COMPARTMENT
    from ..model.regions import compartment_names

    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    _image_axes(ax, image, pixel_size_mm)
    dy, dx = pixel_size_mm
    extent = (0, image.shape[1] * dx, image.shape[0] * dy, 0)
    labels = compartments.labels
    found = sorted(int(v) for v in np.unique(labels[labels >= FIRST_COMPARTMENT]))
    names = compartment_names(labels, pixel_size_mm) if found else {}
    colours = plt.get_cmap("tab10")
    tint = np.zeros(image.shape + (4,))
    for k, label in enumerate(found):
        tint[labels == label] = (*colours(k % 10)[:3], 0.35)
        rows, cols = np.nonzero(labels == label)
        ax.text((cols.mean() + 0.5) * dx, (rows.mean() + 0.5) * dy, str(k + 1), color="white", fontsize=12,
                ha="center", va="center", weight="bold")
        ax.plot([], [], "s", color=colours(k % 10), label=names[label])
    ax.imshow(tint, extent=extent, interpolation="nearest")
    septa = np.ma.masked_where(~compartments.septa, np.ones(image.shape))
    ax.imshow(septa, cmap=matplotlib.colors.ListedColormap(["red"]), extent=extent, interpolation="nearest")
    ax.plot([], [], "-", color="red", label="septa found")
    ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    ax.set_title(f"muscle compartments found at the septa of I0: {len(found)}" if found else
                 "no muscle compartments found: no septum closes one", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def diagnosis_figure(path: Path, image: np.ndarray, pixel_size_mm, maps, mesh, patch_elements: np.ndarray | None = None,
                     place: str = "", title: str = "") -> Path:
    """The residual of the identified model (u_model - u_measured) as arrows coloured by length (mm, colour bar)
    on the unloaded image, the 30-degree sectors of `regions` about the leg centre with their anatomical names, and
    the place of the proposed local stiffness change shaded; `title` says which garment level it is, when several."""
    from matplotlib.collections import PolyCollection
    from scipy.spatial import cKDTree

    positions = np.asarray(maps.positions_mm, float)
    residual = np.asarray(maps.residual_mm, float)
    centre = np.asarray(maps.centre_mm, float)
    figure, ax = plt.subplots(figsize=(8.0, 7.5))
    _image_axes(ax, image, pixel_size_mm)
    if patch_elements is not None and len(patch_elements):
        corners = mesh.nodes[mesh.elements[np.asarray(patch_elements), :3]]
        ax.add_collection(PolyCollection(corners, facecolors="tab:orange", edgecolors="none", alpha=0.45,
                                         label=f"local stiffness change: {place}"))
    radius = 0.5 * float(min(image.shape[0] * pixel_size_mm[0], image.shape[1] * pixel_size_mm[1]))
    for k, name in enumerate(maps.sector_names):
        angle = np.radians(k * 360.0 / len(maps.sector_names))
        ax.plot([centre[0], centre[0] + radius * np.cos(angle)], [centre[1], centre[1] - radius * np.sin(angle)],
                color="white", linewidth=0.5, alpha=0.5)
        middle = np.radians(maps.sector_centre_deg[k])
        ax.text(centre[0] + 0.9 * radius * np.cos(middle), centre[1] - 0.9 * radius * np.sin(middle),
                name.split(" sector ")[0] + f"\n{maps.sector_centre_deg[k]:.0f} deg", color="white", fontsize=6,
                ha="center", va="center")
    length = np.hypot(residual[:, 0], residual[:, 1])
    largest = float(length.max()) if length.size else 1.0
    places = np.unique(positions, axis=0)   # several garment levels share their windows' places
    spacing = float(np.median(cKDTree(places).query(places, k=2)[0][:, 1])) if len(places) > 1 else 1.0
    scale = largest / (1.5 * spacing) if largest > 0 else 1.0
    arrows = ax.quiver(positions[:, 0], positions[:, 1], residual[:, 0], residual[:, 1], length, cmap="magma",
                       angles="xy", scale_units="xy", scale=scale, width=0.003)
    figure.colorbar(arrows, ax=ax, shrink=0.8, label="residual u_model - u_measured (mm)")
    reference = float(f"{largest:.1g}") if largest > 0 else 1.0
    ax.quiverkey(arrows, 0.80, 0.10, reference, f"{reference:g} mm", labelpos="E", coordinates="axes", color="white",
                 labelcolor="white")
    if patch_elements is not None and len(patch_elements):
        ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title((f"{title}\n" if title else "") + f"residual of the identified model, arrows x{1 / scale:.0f}"
                 + (f"\nlargest share: {maps.worst_region}" if maps.worst_region else ""), fontsize=9, loc="left")
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


# ----------------------------------------------------------------------------- the report's figures

TISSUE_COLOURS = {1: ("fat", "#f2c14e"), 2: ("muscle", "#c0392b"), 3: ("bone", "#ecf0f1")}
COMPARTMENT_COLOURS = "tab10"


def _save(figure, path: Path) -> Path:
    figure.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(figure)
    return Path(path)


def _extent(shape, pixel_size_mm) -> tuple[float, float, float, float]:
    return (0.0, shape[1] * pixel_size_mm[1], shape[0] * pixel_size_mm[0], 0.0)


def _landmark_markers(ax, landmarks: dict[str, tuple[float, float]], colour: str = "white") -> None:
    """Numbered markers at the landmarks, named in the legend (1 great_saphenous, ...)."""
    for number, (name, (x, y)) in enumerate(landmarks.items(), start=1):
        ax.plot(x, y, "o", markersize=9, markerfacecolor="black", markeredgecolor=colour, markeredgewidth=1.2,
                label=f"{number} {name}")
        ax.text(x, y, str(number), color=colour, fontsize=6.5, ha="center", va="center", weight="bold")


def images_figure(path: Path, unloaded: np.ndarray, loaded: np.ndarray, pixel_size_mm,
                  titles=("I0, without the garment", "I1, with the garment (aligned on the bones)")) -> Path:
    """The two slices side by side (Avril et al. Fig. 1), axes in mm."""
    figure, axes = plt.subplots(1, 2, figsize=(11.0, 5.2))
    for ax, image, title in zip(axes, (unloaded, loaded), titles):
        _image_axes(ax, image, pixel_size_mm)
        ax.set_title(title, fontsize=10)
    return _save(figure, path)


def segmentation_figure(path: Path, image: np.ndarray, labels: np.ndarray, mesh, pixel_size_mm,
                        landmarks: dict[str, tuple[float, float]], warnings=None) -> Path:
    """The tissues of I0 tinted (fat, muscle, bone, compartments), the mesh's edges and the named landmarks
    (Avril et al. Fig. 2), and a ringed marker with a few words at each place the labels are unsure of
    (`warnings`, `imaging.segment.SegmentationWarning`s; by default the checks of these labels)."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Patch

    from ..imaging.segment import segmentation_checks

    warnings = segmentation_checks(labels, pixel_size_mm) if warnings is None else list(warnings)

    figure, ax = plt.subplots(figsize=(8.0, 7.5))
    _image_axes(ax, image, pixel_size_mm)
    tint = np.zeros(labels.shape + (4,))
    handles = []
    for label, (name, colour) in TISSUE_COLOURS.items():
        tint[labels == label] = (*matplotlib.colors.to_rgb(colour), 0.40)
        handles.append(Patch(color=colour, alpha=0.6, label=name))
    compartments = sorted(int(v) for v in np.unique(labels[labels >= 4]))
    cycle = plt.get_cmap(COMPARTMENT_COLOURS)
    for k, label in enumerate(compartments):
        tint[labels == label] = (*cycle(k % 10)[:3], 0.40)
        handles.append(Patch(color=cycle(k % 10), alpha=0.6, label=f"muscle compartment {k + 1}"))
    ax.imshow(tint, extent=_extent(labels.shape, pixel_size_mm), interpolation="nearest")
    corners = mesh.nodes[mesh.elements[:, :3]]
    edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [2, 0]]])
    ax.add_collection(LineCollection(edges, colors="black", linewidths=0.25, alpha=0.7))
    handles.append(matplotlib.lines.Line2D([], [], color="black", linewidth=0.6,
                                           label=f"mesh: {len(mesh.elements)} {mesh.element_type}"))
    _landmark_markers(ax, landmarks)
    for warning in warnings:
        x, y = warning.position_mm
        ax.plot(x, y, "o", markersize=16, markerfacecolor="none", markeredgecolor="magenta", markeredgewidth=1.8)
        ax.annotate(warning.short, (x, y), xytext=(10, 10), textcoords="offset points", fontsize=7, color="magenta",
                    bbox={"boxstyle": "round,pad=0.2", "facecolor": "black", "alpha": 0.7, "linewidth": 0})
    if warnings:
        handles.append(matplotlib.lines.Line2D([], [], marker="o", linestyle="none", markersize=9, markerfacecolor="none",
                                               markeredgecolor="magenta", label=f"segmentation unsure ({len(warnings)})"))
    _zoom_to(ax, labels > 0, pixel_size_mm)
    landmark_handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + landmark_handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    ax.set_title("segmentation of I0 and the finite-element mesh"
                 + (f"; {len(warnings)} place{'s' if len(warnings) > 1 else ''} unsure" if warnings else ""), fontsize=10)
    return _save(figure, path)


def contour_distance_figure(path: Path, panels: list[tuple[str, np.ndarray]], unloaded: np.ndarray, pixel_size_mm,
                            d_max_mm: float, warped: np.ndarray | None = None) -> Path:
    """Contour distances d_k (Avril et al. sec. 2.2.5, Fig. 4) on a dimmed I0, one panel per model on a shared
    scale (mm); with `warped`, the warped I1 and the target I0 first."""
    images = [("I1 warped by the identified model", warped), ("target I0", unloaded)] if warped is not None else []
    count = len(images) + len(panels)
    figure, axes = plt.subplots(1, count, figsize=(4.6 * count, 4.8), squeeze=False)
    axes = axes[0]
    for ax, (title, image) in zip(axes, images):
        _image_axes(ax, image, pixel_size_mm)
        ax.set_title(title, fontsize=9)
    shown = None
    for ax, (title, distance) in zip(axes[len(images):], panels):
        _image_axes(ax, unloaded, pixel_size_mm)
        ax.images[0].set_alpha(0.45)
        shown = ax.imshow(np.ma.masked_invalid(distance), cmap="viridis", vmin=0.0, vmax=d_max_mm,
                          extent=_extent(distance.shape, pixel_size_mm), interpolation="nearest")
        _zoom_to(ax, np.isfinite(distance), pixel_size_mm)
        ax.set_title(title, fontsize=9)
    if shown is not None:
        figure.colorbar(shown, ax=list(axes[len(images):]), shrink=0.8, label="contour distance d_k (mm)")
    return _save(figure, path)


def pressure_figure(path: Path, pressure_kPa: np.ndarray, pixel_size_mm, landmarks: dict[str, tuple[float, float]],
                    landmark_values: dict[str, tuple[float, float]]) -> Path:
    """Hydrostatic pressure -tr(sigma)/3 in the soft tissues at the central parameters (Avril et al. Fig. 5):
    colour bar in kPa with mmHg beside it, the landmarks numbered and named with their mean +- standard deviation
    (`landmark_values`: the parameters' draws and the tension's uncertainty together, `report.pressure_spreads`),
    to the digits that deviation allows."""
    figure, ax = plt.subplots(figsize=(8.6, 7.2))
    finite = pressure_kPa[np.isfinite(pressure_kPa)]
    low, high = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
    shown = ax.imshow(np.ma.masked_invalid(pressure_kPa), cmap="cividis", vmin=low, vmax=high,
                      extent=_extent(pressure_kPa.shape, pixel_size_mm), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    ax.set_facecolor("#dddddd")
    bar = figure.colorbar(shown, ax=ax, shrink=0.8, pad=0.12)
    bar.ax.yaxis.set_ticks_position("left")
    bar.ax.yaxis.set_label_position("left")
    bar.set_label("hydrostatic pressure (kPa)")
    mmhg = bar.ax.secondary_yaxis("right", functions=(lambda kpa: kpa * MMHG_PER_KPA, lambda mm: mm / MMHG_PER_KPA))
    mmhg.set_ylabel("(mmHg)")
    named = {}
    for name, position in landmarks.items():
        mean, std = landmark_values.get(name, (np.nan, np.nan))
        named[f"{name}: {with_uncertainty(mean, std, 'kPa')} "
              f"({with_uncertainty(mean * MMHG_PER_KPA, std * MMHG_PER_KPA, 'mmHg')})"] = position
    _landmark_markers(ax, named)
    _zoom_to(ax, np.isfinite(pressure_kPa), pixel_size_mm)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=8, frameon=False)
    ax.set_title("hydrostatic pressure at the central parameters; landmarks: mean +- std (parameters and tension)",
                 fontsize=9)
    return _save(figure, path)


def _scattered_map(positions_mm: np.ndarray, values: np.ndarray, mask: np.ndarray, pixel_size_mm) -> np.ndarray:
    """Values at scattered points interpolated linearly over the pixels of `mask` (NaN elsewhere and outside the
    points' convex hull)."""
    from scipy.interpolate import griddata

    rows, cols = np.nonzero(mask)
    out = np.full(mask.shape, np.nan)
    if len(positions_mm) >= 3:
        out[rows, cols] = griddata(positions_mm, values, ((cols + 0.5) * pixel_size_mm[1], (rows + 0.5) * pixel_size_mm[0]),
                                   method="linear")
    return out


def _zoom_to(ax, mask: np.ndarray, pixel_size_mm, margin_mm: float = 6.0) -> None:
    """Show only the part of the image around the mask (the leg), axes still in mm of the image frame."""
    rows, cols = np.nonzero(mask)
    if rows.size:
        dy, dx = pixel_size_mm
        ax.set_xlim(cols.min() * dx - margin_mm, (cols.max() + 1) * dx + margin_mm)
        ax.set_ylim((rows.max() + 1) * dy + margin_mm, rows.min() * dy - margin_mm)


def residual_figure(path: Path, image: np.ndarray, leg: np.ndarray, pixel_size_mm, positions_mm: np.ndarray,
                    measured_mm: np.ndarray | None, fits: list[tuple[str, np.ndarray]], centre_mm) -> Path:
    """For each model (the identified one, then each refit, in columns): the measured and the model's
    displacements as arrows (top row, when the measurements are known), the residual's magnitude
    |u_model - u_measured| (middle row) and its radial component, + outwards, on a diverging map (bottom row).
    Every row shares one scale across models."""
    positions = np.asarray(positions_mm, float)
    rows = 3 if measured_mm is not None else 2
    figure, axes = plt.subplots(rows, len(fits), figsize=(4.2 * len(fits) + 1.4, 4.2 * rows), squeeze=False,
                                layout="constrained")
    radial_unit = positions - np.asarray(centre_mm, float)
    radial_unit /= np.maximum(np.linalg.norm(radial_unit, axis=1, keepdims=True), 1e-12)
    largest = max(float(np.linalg.norm(r, axis=1).max()) for _, r in fits) or 1.0
    radial_max = max(float(np.abs((r * radial_unit).sum(axis=1)).max()) for _, r in fits) or 1.0
    first = 0
    if measured_mm is not None:
        measured = np.asarray(measured_mm, float)
        reference = float(f"{float(np.linalg.norm(measured, axis=1).max()) / 2:.1g}") or 1.0
        scale = reference / 5.0            # a displacement of `reference` mm is drawn 5 mm long
        for column, (title, residual) in enumerate(fits):
            ax = axes[0, column]
            _image_axes(ax, image, pixel_size_mm)
            ax.images[0].set_alpha(0.5)
            options = dict(angles="xy", scale_units="xy", scale=scale, width=0.005)
            measured_arrows = ax.quiver(positions[:, 0], positions[:, 1], measured[:, 0], measured[:, 1],
                                        color="black", label="measured", **options)
            ax.quiver(positions[:, 0], positions[:, 1], measured[:, 0] + residual[:, 0],
                      measured[:, 1] + residual[:, 1], color="tab:orange", label="model", alpha=0.85, **options)
            ax.quiverkey(measured_arrows, 0.80, 0.06, reference, f"{reference:g} mm", labelpos="N", coordinates="axes",
                         fontproperties={"size": 7})
            ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
            _zoom_to(ax, leg, pixel_size_mm)
            ax.set_title(f"{title}\ndisplacements", fontsize=9)
        first = 1
    for column, (title, residual) in enumerate(fits):
        magnitude = np.linalg.norm(residual, axis=1)
        radial = (residual * radial_unit).sum(axis=1)
        for row, values, cmap, limits, heading in (
                (first, magnitude, "magma", (0.0, largest), f"|residual|, RMS {np.sqrt(np.mean(magnitude ** 2)):.3f} mm"),
                (first + 1, radial, "RdBu_r", (-radial_max, radial_max), "radial residual")):
            ax = axes[row, column]
            _image_axes(ax, image, pixel_size_mm)
            ax.images[0].set_alpha(0.35)
            shown = ax.imshow(np.ma.masked_invalid(_scattered_map(positions, values, leg, pixel_size_mm)), cmap=cmap,
                              vmin=limits[0], vmax=limits[1], extent=_extent(leg.shape, pixel_size_mm),
                              interpolation="nearest")
            ax.plot(positions[:, 0], positions[:, 1], ".", color="white", markersize=1.2)
            _zoom_to(ax, leg, pixel_size_mm)
            ax.set_title(f"{title}\n{heading}", fontsize=9)
            if column == len(fits) - 1:
                label = ("|u_model - u_measured| (mm)" if row == first
                         else "radial residual (mm, + the model lies outwards)")
                figure.colorbar(shown, ax=list(axes[row]), shrink=0.9, label=label)
    return _save(figure, path)


def ranking_figure(path: Path, ranking: list[dict], alpha: float) -> Path:
    """The effect ranking of the diagnosis: -log10 of each effect's p-value (corrected for correlated residuals)
    as bars, most likely at the top, with the significance line at alpha."""
    names = [score["effect"] for score in ranking][::-1]
    strength = [-np.log10(max(score["p_value"], 1e-300)) for score in ranking][::-1]
    colours = ["tab:red" if score["significant"] else "tab:gray" for score in ranking][::-1]
    figure, ax = plt.subplots(figsize=(7.5, 0.45 * len(names) + 1.6))
    ax.barh(names, strength, color=colours)
    ax.axvline(-np.log10(alpha), color="black", linestyle="--", label=f"significance, alpha = {alpha:g}")
    ax.set_xlabel("-log10 p-value of the score test (corrected for correlated residuals)")
    ax.set_ylabel("catalog effect")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("which missing effect the residual points to (red: significant)", fontsize=10)
    return _save(figure, path)


def misfit_figure(path: Path, fits: list[tuple[str, float]], explained_factor: float,
                  floor_agreement: float | None = None) -> Path:
    """Misfit over its noise floor for the identified model and each refit, with the floor (1), the ratio up to which
    the error model agrees with the measured errors (a refit above it has not reached the floor) and the level at
    which an effect is said to explain the residual."""
    labels = [label for label, _ in fits]
    ratios = [ratio for _, ratio in fits]
    figure, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(fits) + 2.0), 4.2))
    bars = ax.bar(labels, ratios, color=["tab:gray"] + ["tab:blue"] * (len(fits) - 1))
    ax.bar_label(bars, labels=[f"{r:.2f}x" for r in ratios], fontsize=8)
    ax.axhline(1.0, color="black", linestyle="-", label="noise floor")
    if floor_agreement is not None:
        ax.axhline(floor_agreement, color="black", linestyle=":",
                   label=f"at the floor within the error model's agreement ({floor_agreement:g}x)")
    ax.axhline(explained_factor, color="black", linestyle="--", label=f"explained ({explained_factor:g}x the floor)")
    if max(ratios) > 20 * min(ratios):
        ax.set_yscale("log")
    ax.set_ylabel("misfit / noise floor")
    ax.tick_params(axis="x", labelsize=8, labelrotation=15)
    ax.legend(fontsize=8)
    ax.set_title("misfit before and after the refits", fontsize=10)
    return _save(figure, path)


def intervals_figure(path: Path, names: list[str], units: list[str], identified, lower, upper, poorly: list[str],
                     title: str, truth: dict | None = None) -> Path:
    """The Monte-Carlo intervals as error bars, one small panel per parameter in its own unit (kPa, or the
    effect's), the identified value as the point; not identifiable or poorly identified ones in red; the
    phantom's truth as a star when known."""
    identified, lower, upper = (np.asarray(v, float) for v in (identified, lower, upper))
    figure, axes = plt.subplots(1, len(names), figsize=(max(5.0, 1.9 * len(names) + 1.0), 3.8), squeeze=False)
    for k, (ax, name) in enumerate(zip(axes[0], names)):
        colour = "tab:red" if name in poorly else "tab:blue"
        ax.errorbar([0], [identified[k]], yerr=[[identified[k] - lower[k]], [upper[k] - identified[k]]], fmt="o",
                    color=colour, capsize=8, linewidth=2, label="identified, interval")
        if truth and name in truth:
            ax.plot([0], [truth[name]], "k*", markersize=10, label="truth (phantom)")
        ax.set_xticks([0], [name], fontsize=8)
        ax.set_xlim(-1, 1)
        ax.set_ylabel(units[k], fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_title("NOT identifiable" if name in poorly else "identifiable", fontsize=8, color=colour)
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, bbox_to_anchor=(0.5, -0.04))
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    return _save(figure, path)


def band_figure(path: Path, band: dict, direction) -> Path:
    """The explicit garment band on the leg (pressures.json "band", `garment_state`), against the angle around the
    leg (display angle, the anatomical direction named above each 45 deg by `direction`): the contact pressure of
    each skin face in kPa and mmHg, each skin node's contact status as a strip at the bottom, the bridges shaded
    with their length and gap; the band's hoop force; with friction, the shear and the slip."""
    profile, faces, stations = band["profile"], band["faces"], band["stations"]
    order = np.argsort(profile["angle_deg"])
    angle = np.asarray(profile["angle_deg"])[order]
    status = np.asarray(profile["status"])[order]
    friction = band["friction_mu"] > 0
    rows = 3 if friction else 2
    figure, axes = plt.subplots(rows, 1, figsize=(9.0, 2.6 * rows + 0.8), sharex=True)
    ax = axes[0]
    face_order = np.argsort(faces["angle_deg"])
    ax.plot(np.asarray(faces["angle_deg"])[face_order], np.asarray(faces["pressure_kPa"])[face_order],
            color="tab:blue", linewidth=1.2, label="contact pressure (face mean)")
    strip = ax.get_xaxis_transform()   # x in degrees, y in the axes' height
    for code, name, colour in ((0, "open: the band bridges", "tab:red"), (1, "sticking", "tab:cyan"),
                               (2, "slipping" if friction else "in contact, frictionless", "tab:green")):
        shown = status == code
        if shown.any():
            ax.scatter(angle[shown], np.full(shown.sum(), 0.03), transform=strip, marker="|", s=40, color=colour,
                       label=f"skin node {name}")
    for bridge in band["bridges"]:
        low, high = sorted((bridge["start_deg"], bridge["end_deg"]))
        spans = [(low, high)] if high - low <= 180.0 else [(0.0, low), (high, 360.0)]   # across 0 deg
        for start, end in spans:
            ax.axvspan(start, end, color="tab:red", alpha=0.12, linewidth=0)
        ax.text(0.5 * (low + high) if high - low <= 180.0 else high, 0.5, f"bridge {bridge['length_mm']:.1f} mm,\n"
                f"gap {bridge['max_gap_mm']:.2f} mm", transform=strip, ha="center", fontsize=7, color="tab:red")
    ax.set_ylim(bottom=0.0)
    ax.set_ylabel("contact pressure (kPa)")
    mmhg = ax.secondary_yaxis("right", functions=(lambda kpa: kpa * MMHG_PER_KPA, lambda mm: mm / MMHG_PER_KPA))
    mmhg.set_ylabel("(mmHg)")
    ax.legend(loc="lower right", fontsize=7, ncol=2, bbox_to_anchor=(1.0, 0.06))
    ax.set_title(f"the garment band on the leg (friction mu = {band['friction_mu']:g}); mean contact pressure "
                 f"{band['contact_pressure_kPa']['mean']:.3g} kPa", fontsize=9)
    names = ax.secondary_xaxis("top")
    ticks = np.arange(0.0, 360.0, 45.0)
    names.set_xticks(ticks, [direction(t) for t in ticks], fontsize=7)
    station_order = np.argsort(stations["angle_deg"])
    tension = np.asarray(stations["hoop_tension_N_per_mm"])[station_order]
    axes[1].plot(np.asarray(stations["angle_deg"])[station_order], tension, color="tab:purple")
    mean = float(tension.mean())
    axes[1].set_ylim(min(tension.min(), 0.98 * mean), max(tension.max(), 1.02 * mean))   # +-2 % at least: not noise
    axes[1].set_ylabel("band hoop force (N/mm)")
    if friction:
        ax = axes[2]
        ax.plot(np.asarray(faces["angle_deg"])[face_order], np.asarray(faces["shear_kPa"])[face_order],
                color="tab:orange")
        ax.set_ylabel("friction shear, face mean (kPa)", color="tab:orange")
        slip = ax.twinx()
        slip.plot(angle, np.asarray(profile["slip_mm"])[order], color="tab:brown")
        slip.set_ylabel("slip since first touch (mm)", color="tab:brown")
    axes[-1].set_xlabel("angle around the leg (deg, counter-clockwise on the image, 90 at the top)")
    axes[-1].set_xlim(0.0, 360.0)
    axes[-1].set_xticks(np.arange(0.0, 361.0, 45.0))
    figure.tight_layout()
    return _save(figure, path)


# ----------------------------------------------------------------------------- the study report's figures


def save_figure(figure, path: Path) -> Path:
    """Write a figure of the study report (PNG, the report's resolution) and free it."""
    return _save(figure, path)


def study_profile_figure(heights_mm, panels, named_heights: dict[str, float], kind: str, *, mmhg: bool = False,
                         reference: float | None = None):
    """Quantities along the leg, one panel each: panels are (label, values, low, high, unit) by height, low/high
    the band (None: no band). The named heights of the compression standard (B, B1, C, D) are dashed lines."""
    from ..engine.results import MMHG_PER_KPA

    heights = np.asarray(heights_mm, float)
    columns = min(len(panels), 2)
    rows = int(np.ceil(len(panels) / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(5.2 * columns, 3.0 * rows), squeeze=False,
                                constrained_layout=True)
    for ax, (label, values, low, high, unit) in zip(axes.ravel(), panels):
        if low is not None and high is not None:
            ax.fill_between(heights, np.asarray(low, float), np.asarray(high, float), color="#5b8db8", alpha=0.3,
                            linewidth=0, label="95 % band" if kind != "pressure" else "+- 2 std")
        ax.plot(heights, np.asarray(values, float), "o-", color="#1f4e79", markersize=4, label=label)
        if reference is not None:
            ax.axhline(reference, color="0.3", linestyle=":", linewidth=1)
        for name, height in named_heights.items():
            ax.axvline(height, color="0.5", linestyle="--", linewidth=0.8)
            ax.annotate(name, (height, 1.0), xycoords=("data", "axes fraction"), xytext=(2, -10),
                        textcoords="offset points", fontsize=8, color="0.3")
        ax.set_xlabel("height along the leg (mm)")
        ax.set_ylabel(f"{label if kind == 'parameter' else kind} ({unit})" if unit else label)
        ax.set_title(label, fontsize=10)
        if mmhg:
            ax.secondary_yaxis("right", functions=(lambda p: p * MMHG_PER_KPA, lambda p: p / MMHG_PER_KPA)
                               ).set_ylabel("mmHg")
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    return figure


def study_distribution_figure(panels):
    """Each parameter over the cases: panels are (name, case names, values, low, high); a dot and its 95 % interval
    per case, the median as a line."""
    columns = min(len(panels), 2)
    rows = int(np.ceil(len(panels) / columns))
    count = len(panels[0][1]) if panels else 0
    figure, axes = plt.subplots(rows, columns, figsize=(max(5.2, 0.35 * count + 2) * columns, 3.0 * rows),
                                squeeze=False, constrained_layout=True)
    for ax, (name, cases, values, low, high) in zip(axes.ravel(), panels):
        values, low, high = (np.asarray(v, float) for v in (values, low, high))
        positions = np.arange(len(cases))
        ax.errorbar(positions, values, yerr=[values - low, high - values], fmt="o", color="#1f4e79", capsize=2,
                    markersize=4)
        ax.axhline(float(np.median(values)), color="#c0392b", linewidth=1, label="median")
        ax.set_xticks(positions, cases, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(f"{name} (kPa)")
        ax.set_title(name, fontsize=10)
        ax.legend(fontsize=8, loc="best")
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    return figure
