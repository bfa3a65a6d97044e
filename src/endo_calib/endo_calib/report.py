"""The calibration report figure (after the seed paper's Figures 2 and 3).

Six panels, per channel curves overlaid, and a column of text:

1. mean raw value at the centre of the field of view against gray level (the
   paper's "camera response against gray level"), with the fitted curve; a
   card whose centre is saturated is marked "saturated: excluded";
2. the inverse response g(v) with the per-(pixel, level) samples it was
   fitted to (coloured by reflectance, with a colour bar), the range of raw
   values the data covered and the extrapolated rest shaded, and the truth
   overlaid when a simulated recording's truth lies beside the input;
3. the light map L(x);
4. the card before correction (raw mean of one level);
5. the same card after correction, divided by the known geometry term;
6. the fit residuals v̄ − f(ρ·L·G) of that level in raw values;
7. text: the inputs (file, size, digest, topics, camera_info, card) and the
   fit statistics (levels, frames, usable and saturated shares, residual,
   observed range, how the top was found).

Images use perceptual colour maps (viridis, cividis) with colour bars; value
axes stay within the data's range (0 .. 2^bits − 1 raw values, 0 .. 1 of g).
Drawn with matplotlib's Agg backend, so it needs no display.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from endo_calib.calibration import PhotometricCalibration
from endo_calib.errors import CalibrationError
from endo_calib.fit import FitReport

_COLOURS = {"mono": "k", "red": "tab:red", "green": "tab:green", "blue": "tab:blue"}
#: The annotation of a card left out of the fit because its centre saturates.
SATURATED_NOTE = "saturated: excluded"


def card_nonuniformity(
    image: NDArray[np.floating], mask: NDArray[np.bool_], block: int = 8
) -> float:
    """Low-frequency non-uniformity of a card image: std/mean of its block means.

    image: (H, W) float (e.g. a corrected card divided by its geometry term).
    mask: (H, W) bool pixels to use; only blocks entirely inside it count.
    block: block side in pixels; averaging over blocks keeps pixel noise out of a
        figure meant to measure shading left after correction.
    Returns std/mean (a fraction) of the block means.
    """
    h, w = image.shape
    hb, wb = h // block, w // block
    good = mask & np.isfinite(image)
    values = np.where(good, image, 0.0)[: hb * block, : wb * block]
    sums = values.reshape(hb, block, wb, block).sum(axis=(1, 3))
    counts = good[: hb * block, : wb * block].reshape(hb, block, wb, block).sum(axis=(1, 3))
    full = counts == block * block
    if full.sum() < 2:
        raise CalibrationError("card_nonuniformity needs at least two full blocks inside the mask")
    means = sums[full] / counts[full]
    return float(np.std(means) / np.mean(means))


def write_report(
    report: FitReport,
    path: str | Path,
    *,
    light_source: str = "model",
    truth_inverse_response: NDArray[np.float64] | None = None,
    inputs: dict[str, Any] | None = None,
) -> Path:
    """Draw the report of a gray-card fit into a PNG.

    Args:
        report: what :func:`endo_calib.fit.fit_gray_card` returned.
        path: the PNG to write (parent directories are created).
        light_source: the light map shown, as the calibration will use it:
            "model" or "pixels" (see ``PhotometricCalibration``).
        truth_inverse_response: optional (2^bits,) known g to overlay (simulations).
        inputs: the calibration's provenance (:mod:`endo_io.provenance`), shown as text.

    Returns:
        The path written.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = report_figure(
        report,
        light_source=light_source,
        truth_inverse_response=truth_inverse_response,
        inputs=inputs,
    )
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def report_figure(
    report: FitReport,
    *,
    light_source: str = "model",
    truth_inverse_response: NDArray[np.float64] | None = None,
    inputs: dict[str, Any] | None = None,
) -> plt.Figure:
    """The report figure of :func:`write_report` (the caller closes it).

    Axes are labelled ``ax.get_label()`` = "response", "inverse", "light",
    "before", "after", "residual" and "text" so that tests can find them.
    """
    fov = report.fov_mask
    height, width = fov.shape
    n_levels = len(report.levels)
    rho = np.array([lv["reflectance"] * lv["exposure"] for lv in report.levels])
    order = np.argsort(rho)
    mid = int(order[len(order) // 2])
    # Centre patch: FOV pixels within 5% of the image diagonal of the centre of the FOV.
    yy, xx = np.nonzero(fov)
    cy, cx = yy.mean(), xx.mean()
    radius = 0.05 * np.hypot(width, height)
    centre = fov & (
        (np.arange(height)[:, None] - cy) ** 2 + (np.arange(width)[None, :] - cx) ** 2 <= radius**2
    )
    rng = np.random.default_rng(0)
    sample = rng.choice(yy.size, min(yy.size, 3000), replace=False)
    top = (1 << report.bit_depth) - 1
    levels_norm = matplotlib.colors.Normalize(float(rho.min()), float(rho.max()))
    level_colours = matplotlib.colormaps["viridis"]

    fig = plt.figure(figsize=(20, 9))
    grid = fig.add_gridspec(2, 4, width_ratios=[1, 1, 1, 0.85])
    ax_level = fig.add_subplot(grid[0, 0], label="response")
    ax_g = fig.add_subplot(grid[0, 1], label="inverse")
    ax_light = fig.add_subplot(grid[0, 2], label="light")
    ax_before = fig.add_subplot(grid[1, 0], label="before")
    ax_after = fig.add_subplot(grid[1, 1], label="after")
    ax_resid = fig.add_subplot(grid[1, 2], label="residual")
    ax_text = fig.add_subplot(grid[:, 3], label="text")
    excluded: set[int] = set()
    for c, (name, fit) in enumerate(report.channels.items()):
        colour = _COLOURS.get(name, "k")
        centre_values = np.array(
            [_nanmedian(report.level_means[k][..., c][centre]) for k in range(n_levels)]
        )
        seen = np.isfinite(centre_values)
        ax_level.plot(
            rho[order][seen[order]],
            centre_values[order][seen[order]],
            "o",
            color=colour,
            label=f"cards, FOV centre ({name})",
        )
        excluded.update(int(index) for index in np.flatnonzero(~seen))
        centre_coeff = np.median(report.coefficient(int(order[-1]))[centre]) / rho[order[-1]]
        centre_light = float(np.median(fit.light_map[centre]))
        grid_rho = np.linspace(0.0, rho.max() * 1.05, 300)
        curve = np.minimum(
            fit.forward(grid_rho * centre_coeff * centre_light * fit.irradiance_scale), top
        )
        observed_top = fit.extent.observed_high if fit.extent is not None else top
        observed = curve <= observed_top
        ax_level.plot(
            grid_rho[observed], curve[observed], "-", color=colour, label=f"fit f ({name})"
        )
        if (~observed).any():
            ax_level.plot(
                grid_rho[~observed], curve[~observed], ":", color=colour,
                label=f"fit f, extrapolated ({name})",
            )
        e_sat = float(fit.forward.inverse(float(top)))
        for k in range(n_levels):
            v = report.level_means[k][..., c][yy[sample], xx[sample]]
            e = (
                (report.coefficient(k) * fit.light_map)[yy[sample], xx[sample]]
                * fit.irradiance_scale
                / e_sat
            )
            ax_g.plot(v, e, ".", ms=1.5, color=level_colours(levels_norm(rho[k])), alpha=0.4)
        ax_g.plot(
            np.arange(top + 1),
            fit.inverse_response.lut,
            "-",
            color=colour,
            lw=1.5,
            label=f"fitted g ({name})",
        )
        if fit.extent is not None and c == 0:
            low, high = fit.extent.observed_low, fit.extent.observed_high
            if high < top:
                ax_g.axvspan(high, top, color="0.85", zorder=0, label="extrapolated (above data)")
            if low > 0:
                ax_g.axvspan(0, low, color="0.93", zorder=0, label="extrapolated (below data)")
    for card in sorted(excluded):
        ax_level.annotate(
            f"ρ={rho[card]:g}: {SATURATED_NOTE}",
            xy=(rho[card], top),
            # below the curve, clear of it and of the legend in the lower right
            xytext=(rho[card], 0.55 * top - 0.07 * top * (card % 3)),
            ha="right",
            fontsize=8,
            arrowprops={"arrowstyle": "->", "color": "tab:red"},
            color="tab:red",
        )
    if truth_inverse_response is not None and truth_inverse_response.size == top + 1:
        ax_g.plot(
            np.arange(top + 1),
            truth_inverse_response,
            "--",
            color="tab:orange",
            label="truth (simulator)",
        )
    ax_level.set(
        xlabel="gray level (reflectance × exposure)",
        ylabel="raw value at FOV centre (DN)",
        title="camera response vs gray level",
        xlim=(0.0, float(rho.max()) * 1.05),
        ylim=(0.0, float(top)),
    )
    ax_level.axhline(top, color="0.5", lw=0.8, ls="--")
    ax_level.legend(fontsize=7, loc="lower right")
    ax_g.set(
        xlabel="raw value v (DN)",
        ylabel="linear irradiance g(v)",
        title="inverse response (samples coloured by reflectance)",
        xlim=(0.0, float(top)),
        ylim=(0.0, 1.0),
    )
    ax_g.legend(fontsize=7, loc="upper left")
    mappable = matplotlib.cm.ScalarMappable(norm=levels_norm, cmap=level_colours)
    fig.colorbar(mappable, ax=ax_g, fraction=0.046, pad=0.04, label="card reflectance ρ")

    light = PhotometricCalibration.from_fit(report, light_source).light_map
    light_view = light if light.ndim == 2 else light.mean(axis=-1)
    _image(fig, ax_light, np.where(fov, light_view, np.nan), "light map L(x)", "viridis", "L")

    c0 = 0
    raw = report.level_means[mid][..., c0]
    before = np.where(fov, raw / np.nanmedian(raw[fov]), np.nan)
    fit0 = next(iter(report.channels.values()))
    light0 = light if light.ndim == 2 else light[..., 0]
    shading = light0 * report.geometry[mid]
    corrected = fit0.inverse_response(raw) / np.where(fov & (shading > 0), shading, np.nan)
    after = np.where(fov, corrected / np.nanmedian(corrected[fov]), np.nan)
    lo, hi = np.nanpercentile(np.concatenate([before[fov], after[fov]]), [1, 99])
    raw_nu = card_nonuniformity(raw / np.where(fov, report.geometry[mid], 1.0), fov)
    cor_nu = card_nonuniformity(corrected, fov)
    level_rho = report.levels[mid]["reflectance"]
    _image(
        fig, ax_before, before, f"card ρ={level_rho:g} before (raw/median)", "cividis",
        "relative value", (lo, hi),
    )
    _image(
        fig,
        ax_after,
        after,
        f"after: g(v)/(L·G), non-uniformity {100 * cor_nu:.2f}% (raw/G {100 * raw_nu:.1f}%)",
        "cividis",
        "relative value",
        (lo, hi),
    )
    e_mid = report.coefficient(mid) * fit0.light_map * fit0.irradiance_scale
    resid = np.where(fov, raw - fit0.forward(e_mid), np.nan)
    bound = float(np.nanpercentile(np.abs(resid), 99)) or 1.0
    _image(
        fig,
        ax_resid,
        resid,
        f"residual v̄ − f (DN) of ρ={level_rho:g}, RMS all levels {fit0.residual_rms:.2f}",
        "cividis",
        "DN",
        (-bound, bound),
    )
    ax_text.axis("off")
    ax_text.text(
        0.0, 1.0, "\n".join(report_text(report, inputs, sorted(excluded))),
        va="top", ha="left", family="monospace", fontsize=7.5, transform=ax_text.transAxes,
    )
    fig.suptitle(
        f"endo_calib gray-card calibration: {n_levels} levels, {report.bit_depth}-bit, "
        f"{'/'.join(report.channels)}"
    )
    fig.tight_layout()
    return fig


def report_text(
    report: FitReport, inputs: dict[str, Any] | None, excluded: list[int] | None = None
) -> list[str]:
    """The report's text column: inputs, then fit statistics, one item a line."""
    lines = ["INPUTS"]
    inputs = inputs or {}
    source = inputs.get("input") or {}
    if source:
        lines.append(f"file: {source.get('file')}")
        lines.append(f"  {int(source.get('size_bytes', 0)):,} bytes")
        lines.append(f"  sha256 {str(source.get('sha256', ''))[:16]}…")
    else:
        lines.append("file: (not recorded)")
    for key, value in (inputs.get("topics") or {}).items():
        lines.append(f"topic {key}: {value}")
    camera = inputs.get("camera_info") or {}
    if camera:
        k = camera.get("K") or [0.0] * 9
        lines.append(f"camera_info: {camera.get('source')}")
        lines.append(
            f"  {camera.get('width')}x{camera.get('height')}, fx {k[0]:.1f} fy {k[4]:.1f}, "
            f"{camera.get('distortion_model') or 'no'} distortion"
        )
    card = inputs.get("card") or {}
    if card:
        lines.append(f"card distance: {1e3 * float(card.get('distance_m', 0.0)):.1f} mm")
        lines.append(f"card normal: {card.get('normal')}")
    tool = inputs.get("tool") or {}
    if tool:
        lines.append(f"{tool.get('program')} {tool.get('endo3d_version')}, {tool.get('date')}")
    lines += ["", "FIT", f"bit depth {report.bit_depth}, saturation at {report.saturation_value}"]
    lines.append("level  frames usable saturated")
    for k, level in enumerate(report.levels):
        note = f"  {SATURATED_NOTE} at centre" if excluded and k in excluded else ""
        lines.append(
            f"ρ={level['reflectance']:<5g}{level['frames']:>5} "
            f"{100 * level['usable_fraction']:5.0f}% "
            f"{100 * level['saturated_fraction']:6.1f}%{note}"
        )
    for name, fit in report.channels.items():
        lines.append(
            f"{name}: residual RMS {fit.residual_rms:.3f} DN, {fit.iterations} iterations"
            f"{'' if fit.converged else ' (NOT converged)'}"
        )
        if fit.extent is not None:
            top = (1 << report.bit_depth) - 1
            lines.append(
                f"  observed raw values {fit.extent.observed_low}..{fit.extent.observed_high}"
            )
            if fit.extent.observed_high < top - 1:
                lines.append(f"  extrapolated {fit.extent.observed_high + 1}..{top}")
            lines += [f"  top: {part}" for part in _wrap(fit.extent.top_model, 40)]
    return lines


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for word in words:
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return [*lines, line] if line else lines


def _nanmedian(values: NDArray[np.float64]) -> float:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else float("nan")


def _image(
    fig: plt.Figure,
    ax: plt.Axes,
    data: NDArray[np.float64],
    title: str,
    cmap: str,
    unit: str,
    limits: tuple[float, float] | None = None,
) -> None:
    vmin, vmax = limits if limits is not None else (None, None)
    im = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=unit)
