"""Figures a user reads: matplotlib, axes in mm (image frame of I0: x right, y down), colour bars with values
and units, perceptually uniform colour maps. Written as PNG with the Agg backend (no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np

from ..core.digits import PLUS_MINUS, with_uncertainty
from ..core.plotting import (
    extent,
    image_axes,
    landmark_markers,
    plt,
    save,
    scattered_map,
    zoom_to,
)
from ..core.units import MMHG_PER_KPA

# ----------------------------------------------------------------------------- the report's figures

TISSUE_COLOURS = {1: ("fat", "#f2c14e"), 2: ("muscle", "#c0392b"), 3: ("bone", "#ecf0f1")}
COMPARTMENT_COLOURS = "tab10"


def images_figure(path: Path, unloaded: np.ndarray, loaded: np.ndarray, pixel_size_mm,
                  titles=("I0, without the garment", "I1, with the garment (aligned on the bones)")) -> Path:
    """The two slices side by side (Avril et al. Fig. 1), axes in mm."""
    figure, axes = plt.subplots(1, 2, figsize=(11.0, 5.2))
    for ax, image, title in zip(axes, (unloaded, loaded), titles):
        image_axes(ax, image, pixel_size_mm)
        ax.set_title(title, fontsize=10)
    return save(figure, path)


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
    image_axes(ax, image, pixel_size_mm)
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
    ax.imshow(tint, extent=extent(labels.shape, pixel_size_mm), interpolation="nearest")
    corners = mesh.nodes[mesh.elements[:, :3]]
    edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [2, 0]]])
    ax.add_collection(LineCollection(edges, colors="black", linewidths=0.25, alpha=0.7))
    handles.append(matplotlib.lines.Line2D([], [], color="black", linewidth=0.6,
                                           label=f"mesh: {len(mesh.elements)} {mesh.element_type}"))
    landmark_markers(ax, landmarks)
    for warning in warnings:
        x, y = warning.position_mm
        ax.plot(x, y, "o", markersize=16, markerfacecolor="none", markeredgecolor="magenta", markeredgewidth=1.8)
        ax.annotate(warning.short, (x, y), xytext=(10, 10), textcoords="offset points", fontsize=7, color="magenta",
                    bbox={"boxstyle": "round,pad=0.2", "facecolor": "black", "alpha": 0.7, "linewidth": 0})
    if warnings:
        handles.append(matplotlib.lines.Line2D([], [], marker="o", linestyle="none", markersize=9, markerfacecolor="none",
                                               markeredgecolor="magenta", label=f"segmentation unsure ({len(warnings)})"))
    zoom_to(ax, labels > 0, pixel_size_mm)
    landmark_handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + landmark_handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    ax.set_title("segmentation of I0 and the finite-element mesh"
                 + (f"; {len(warnings)} place{'s' if len(warnings) > 1 else ''} unsure" if warnings else ""), fontsize=10)
    return save(figure, path)


def contour_distance_figure(path: Path, panels: list[tuple[str, np.ndarray]], unloaded: np.ndarray, pixel_size_mm,
                            d_max_mm: float, warped: np.ndarray | None = None) -> Path:
    """Contour distances d_k (Avril et al. sec. 2.2.5, Fig. 4) on a dimmed I0, one panel per model on a shared
    scale (mm); with `warped`, the warped I1 and the target I0 first."""
    images = [("I1 warped by the identified model", warped), ("target I0", unloaded)] if warped is not None else []
    count = len(images) + len(panels)
    figure, axes = plt.subplots(1, count, figsize=(4.6 * count, 4.8), squeeze=False)
    axes = axes[0]
    for ax, (title, image) in zip(axes, images):
        image_axes(ax, image, pixel_size_mm)
        ax.set_title(title, fontsize=9)
    shown = None
    for ax, (title, distance) in zip(axes[len(images):], panels):
        image_axes(ax, unloaded, pixel_size_mm)
        ax.images[0].set_alpha(0.45)
        shown = ax.imshow(np.ma.masked_invalid(distance), cmap="viridis", vmin=0.0, vmax=d_max_mm,
                          extent=extent(distance.shape, pixel_size_mm), interpolation="nearest")
        zoom_to(ax, np.isfinite(distance), pixel_size_mm)
        ax.set_title(title, fontsize=9)
    if shown is not None:
        figure.colorbar(shown, ax=list(axes[len(images):]), shrink=0.8, label="contour distance d_k (mm)")
    return save(figure, path)


def pressure_figure(path: Path, pressure_kPa: np.ndarray, pixel_size_mm, landmarks: dict[str, tuple[float, float]],
                    landmark_values: dict[str, tuple[float, float]]) -> Path:
    """Hydrostatic pressure -tr(sigma)/3 in the soft tissues at the central parameters (Avril et al. Fig. 5):
    colour bar in kPa with mmHg beside it, the landmarks numbered and named with their mean ± standard deviation
    (`landmark_values`: the parameters' draws and the tension's uncertainty together, `report.pressure_spreads`),
    to the digits that deviation allows."""
    figure, ax = plt.subplots(figsize=(8.6, 7.2))
    finite = pressure_kPa[np.isfinite(pressure_kPa)]
    low, high = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
    shown = ax.imshow(np.ma.masked_invalid(pressure_kPa), cmap="cividis", vmin=low, vmax=high,
                      extent=extent(pressure_kPa.shape, pixel_size_mm), interpolation="nearest")
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
    landmark_markers(ax, named)
    zoom_to(ax, np.isfinite(pressure_kPa), pixel_size_mm)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=8, frameon=False)
    ax.set_title(f"hydrostatic pressure at the central parameters; landmarks: mean {PLUS_MINUS} std (parameters and "
                 "tension)", fontsize=9)
    return save(figure, path)


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
            image_axes(ax, image, pixel_size_mm)
            ax.images[0].set_alpha(0.5)
            options = dict(angles="xy", scale_units="xy", scale=scale, width=0.005)
            measured_arrows = ax.quiver(positions[:, 0], positions[:, 1], measured[:, 0], measured[:, 1],
                                        color="black", label="measured", **options)
            ax.quiver(positions[:, 0], positions[:, 1], measured[:, 0] + residual[:, 0],
                      measured[:, 1] + residual[:, 1], color="tab:orange", label="model", alpha=0.85, **options)
            ax.quiverkey(measured_arrows, 0.80, 0.06, reference, f"{reference:g} mm", labelpos="N", coordinates="axes",
                         fontproperties={"size": 7})
            ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
            zoom_to(ax, leg, pixel_size_mm)
            ax.set_title(f"{title}\ndisplacements", fontsize=9)
        first = 1
    for column, (title, residual) in enumerate(fits):
        magnitude = np.linalg.norm(residual, axis=1)
        radial = (residual * radial_unit).sum(axis=1)
        for row, values, cmap, limits, heading in (
                (first, magnitude, "magma", (0.0, largest), f"|residual|, RMS {np.sqrt(np.mean(magnitude ** 2)):.3f} mm"),
                (first + 1, radial, "RdBu_r", (-radial_max, radial_max), "radial residual")):
            ax = axes[row, column]
            image_axes(ax, image, pixel_size_mm)
            ax.images[0].set_alpha(0.35)
            shown = ax.imshow(np.ma.masked_invalid(scattered_map(positions, values, leg, pixel_size_mm)), cmap=cmap,
                              vmin=limits[0], vmax=limits[1], extent=extent(leg.shape, pixel_size_mm),
                              interpolation="nearest")
            ax.plot(positions[:, 0], positions[:, 1], ".", color="white", markersize=1.2)
            zoom_to(ax, leg, pixel_size_mm)
            ax.set_title(f"{title}\n{heading}", fontsize=9)
            if column == len(fits) - 1:
                label = ("|u_model - u_measured| (mm)" if row == first
                         else "radial residual (mm, + the model lies outwards)")
                figure.colorbar(shown, ax=list(axes[row]), shrink=0.9, label=label)
    return save(figure, path)


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
    return save(figure, path)


def misfit_figure(path: Path, fits: list[tuple[str, float]], explained_factor: float,
                  floor_agreement: float | None = None) -> Path:
    """`misfit_plot` written to path."""
    return save(misfit_plot(fits, explained_factor, floor_agreement), path)


def misfit_title(count: int) -> str:
    """What the misfit figure compares: the identified model alone (count 1), or it and its refits."""
    if count <= 1:
        return "misfit of the identified model (no refit ran)"
    return "misfit before and after the refit" + ("s" if count > 2 else "")


def misfit_plot(fits: list[tuple[str, float]], explained_factor: float, floor_agreement: float | None = None):
    """Misfit over its noise floor for the identified model and each refit (bars, each ratio written under its bar
    with the model's name), with the floor (1), the ratio up to which the error model agrees with the measured
    errors (a refit above it has not reached the floor) and the level at which an effect is said to explain the
    residual; the lines' legend beside the axes: no text lies over a line. Returns the figure."""
    labels = [label for label, _ in fits]
    ratios = [ratio for _, ratio in fits]
    figure, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(fits) + 2.0), 4.2))
    positions = np.arange(len(fits))
    ax.bar(positions, ratios, color=["tab:gray"] + ["tab:blue"] * (len(fits) - 1))
    # the ratio under its bar, not over it: a ratio near a line (0.98x under the floor) would be written across it
    ax.set_xticks(positions, [f"{label}\n{ratio:.2f}x" for label, ratio in zip(labels, ratios)])
    ax.axhline(1.0, color="black", linestyle="-", label="noise floor")
    if floor_agreement is not None:
        ax.axhline(floor_agreement, color="black", linestyle=":",
                   label=f"at the floor within the error model's agreement ({floor_agreement:g}x)")
    ax.axhline(explained_factor, color="black", linestyle="--", label=f"explained ({explained_factor:g}x the floor)")
    highest = max(max(ratios), explained_factor)
    if max(ratios) > 20 * min(ratios):
        ax.set_yscale("log")
        ax.set_ylim(top=highest * 1.6)
    else:
        ax.set_ylim(0.0, highest * 1.12)
    ax.set_ylabel("misfit / noise floor")
    ax.tick_params(axis="x", labelsize=8, labelrotation=15)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    ax.set_title(misfit_title(len(fits)), fontsize=10)
    return figure


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
    return save(figure, path)


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
    return save(figure, path)


# ----------------------------------------------------------------------------- the study report's figures


def study_profile_figure(heights_mm, panels, named_heights: dict[str, float], kind: str, *, mmhg: bool = False,
                         reference: float | None = None):
    """Quantities along the leg, one panel each: panels are (label, values, low, high, unit) by height, low/high
    the band (None: no band). The named heights of the compression standard (B, B1, C, D) are dashed lines."""
    from ..core.units import MMHG_PER_KPA

    heights = np.asarray(heights_mm, float)
    columns = min(len(panels), 2)
    rows = int(np.ceil(len(panels) / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(5.2 * columns, 3.0 * rows), squeeze=False,
                                constrained_layout=True)
    for ax, (label, values, low, high, unit) in zip(axes.ravel(), panels):
        if low is not None and high is not None:
            ax.fill_between(heights, np.asarray(low, float), np.asarray(high, float), color="#5b8db8", alpha=0.3,
                            linewidth=0, label="95 % band" if kind != "pressure" else f"{PLUS_MINUS} 2 std")
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
