"""The calibration report figure (after the seed paper's Figures 2 and 3).

Six panels, per channel curves overlaid:

1. mean raw value at the centre of the field of view against gray level (the
   paper's "camera response against gray level"), with the fitted curve;
2. the inverse response g(v) with the per-(pixel, level) samples it was fitted to;
3. the light map L(x) in pseudo-colour;
4. the card before correction (raw mean of one level) in pseudo-colour;
5. the same card after correction, divided by the known geometry term;
6. the fit residuals v̄ − f(ρ·L·G) of that level in raw values.

Drawn with matplotlib's Agg backend, so it needs no display.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from endo_calib.calibration import PhotometricCalibration
from endo_calib.errors import CalibrationError
from endo_calib.fit import FitReport

_COLOURS = {"mono": "k", "red": "tab:red", "green": "tab:green", "blue": "tab:blue"}


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
) -> Path:
    """Draw the report of a gray-card fit into a PNG.

    Args:
        report: what :func:`endo_calib.fit.fit_gray_card` returned.
        path: the PNG to write (parent directories are created).
        light_source: the light map shown, as the calibration will use it:
            "model" or "pixels" (see ``PhotometricCalibration``).
        truth_inverse_response: optional (2^bits,) known g to overlay (simulations).

    Returns:
        The path written.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
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

    fig, axes = plt.subplots(2, 3, figsize=(15, 9))
    ax_level, ax_g, ax_light, ax_before, ax_after, ax_resid = axes.ravel()
    top = (1 << report.bit_depth) - 1
    for c, (name, fit) in enumerate(report.channels.items()):
        colour = _COLOURS.get(name, "k")
        centre_values = [
            float(np.median(report.level_means[k][..., c][centre])) for k in range(n_levels)
        ]
        ax_level.plot(rho[order], np.asarray(centre_values)[order], "o", color=colour, label=name)
        centre_coeff = np.median(report.coefficient(int(order[-1]))[centre]) / rho[order[-1]]
        centre_light = float(np.median(fit.light_map[centre]))
        grid = np.linspace(0.0, rho.max() * 1.05, 200)
        ax_level.plot(
            grid,
            fit.forward(grid * centre_coeff * centre_light * fit.irradiance_scale),
            "-",
            color=colour,
        )
        e_sat = float(fit.forward.inverse(float(top)))
        for k in range(n_levels):
            v = report.level_means[k][..., c][yy[sample], xx[sample]]
            e = (
                (report.coefficient(k) * fit.light_map)[yy[sample], xx[sample]]
                * fit.irradiance_scale
                / e_sat
            )
            ax_g.plot(v, e, ".", ms=1.5, color=plt.cm.viridis(k / max(n_levels - 1, 1)), alpha=0.4)
        ax_g.plot(
            np.arange(top + 1),
            fit.inverse_response.lut,
            "-",
            color=colour,
            lw=1.5,
            label=f"g ({name})",
        )
    if truth_inverse_response is not None:
        ax_g.plot(
            np.arange(top + 1), truth_inverse_response, "--", color="tab:orange", label="truth"
        )
    ax_level.set(
        xlabel="gray level (reflectance × exposure)",
        ylabel="raw value at FOV centre (DN)",
        title="camera response vs gray level",
    )
    ax_level.legend(fontsize=8)
    ax_g.set(xlabel="raw value v (DN)", ylabel="linear irradiance g(v)", title="inverse response")
    ax_g.legend(fontsize=8)

    light = PhotometricCalibration.from_fit(report, light_source).light_map
    light_view = light if light.ndim == 2 else light.mean(axis=-1)
    _image(fig, ax_light, np.where(fov, light_view, np.nan), "light map L(x)", "jet")

    c0 = 0
    raw = report.level_means[mid][..., c0]
    before = np.where(fov, raw / np.median(raw[fov]), np.nan)
    fit0 = next(iter(report.channels.values()))
    light0 = light if light.ndim == 2 else light[..., 0]
    shading = light0 * report.geometry[mid]
    corrected = fit0.inverse_response(raw) / np.where(fov & (shading > 0), shading, np.nan)
    after = np.where(fov, corrected / np.nanmedian(corrected[fov]), np.nan)
    lo, hi = np.nanpercentile(np.concatenate([before[fov], after[fov]]), [1, 99])
    raw_nu = card_nonuniformity(raw / np.where(fov, report.geometry[mid], 1.0), fov)
    cor_nu = card_nonuniformity(corrected, fov)
    level_rho = report.levels[mid]["reflectance"]
    _image(fig, ax_before, before, f"card ρ={level_rho:g} before (raw/median)", "jet", (lo, hi))
    _image(
        fig,
        ax_after,
        after,
        f"after: g(v)/(L·G), non-uniformity {100 * cor_nu:.2f}% (raw/G {100 * raw_nu:.1f}%)",
        "jet",
        (lo, hi),
    )
    e_mid = report.coefficient(mid) * fit0.light_map * fit0.irradiance_scale
    resid = np.where(fov, raw - fit0.forward(e_mid), np.nan)
    bound = float(np.nanpercentile(np.abs(resid), 99)) or 1.0
    _image(
        fig,
        ax_resid,
        resid,
        f"residual v̄ − f (DN), RMS all levels {fit0.residual_rms:.2f}",
        "coolwarm",
        (-bound, bound),
    )
    fig.suptitle(
        f"endo_calib gray-card calibration: {n_levels} levels, {report.bit_depth}-bit, "
        f"{'/'.join(report.channels)}"
    )
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def _image(
    fig: plt.Figure,
    ax: plt.Axes,
    data: NDArray[np.float64],
    title: str,
    cmap: str,
    limits: tuple[float, float] | None = None,
) -> None:
    vmin, vmax = limits if limits is not None else (None, None)
    im = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
