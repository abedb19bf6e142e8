"""Plots of a fit: data and model width along each track with the residual below, and the
corner plot of the posterior (corner package). matplotlib with the Agg backend."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calib.fileio import atomic_write  # noqa: E402


def _save(fig, path) -> Path:
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110), binary=True)
    plt.close(fig)
    return Path(path)


def plot_tracks(pred: dict, path, max_tracks: int = 12) -> Path:
    """Measured (points) and model (MAP line, 68 % band) width vs arc length for each track
    of one scan (``FitResult.predictions[k]``), residuals (mm) below."""
    track = np.asarray(pred["track"])
    ids = list(dict.fromkeys(track.tolist()))[:max_tracks]
    n = len(ids)
    fig, axes = plt.subplots(2 * n, 1, figsize=(10, 2.4 * n + 0.5), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1] * n})
    s = np.asarray(pred["s_mm"])
    y = np.asarray(pred["width_mm"])
    v = np.asarray(pred["valid"]).astype(bool)
    pm = np.asarray(pred["pred_map_mm"])
    lo, hi = np.asarray(pred["pred_lo68_mm"]), np.asarray(pred["pred_hi68_mm"])
    for i, tid in enumerate(ids):
        sel = track == tid
        ax, axr = axes[2 * i, 0], axes[2 * i + 1, 0]
        ax.plot(s[sel & v], y[sel & v], ".", ms=2, color="0.4", label="measured")
        ax.plot(s[sel & ~v], y[sel & ~v], "x", ms=3, color="tab:red", label="not valid")
        ax.fill_between(s[sel], lo[sel], hi[sel], color="tab:blue", alpha=0.3, lw=0)
        ax.plot(s[sel], pm[sel], "-", color="tab:blue", lw=1, label="model (MAP)")
        ax.set_ylabel("width (mm)")
        ax.set_title(f"{pred.get('scan', '')} track {tid}", fontsize=9)
        axr.axhline(0, color="0.6", lw=0.8)
        axr.plot(s[sel & v], (y - pm)[sel & v], ".", ms=2, color="tab:green")
        axr.set_ylabel("resid (mm)")
        if i == 0:
            ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("arc length s (mm)")
    fig.tight_layout()
    return _save(fig, path)


def plot_corner(result, path) -> Path:
    """Corner plot of the posterior draws, MAP marked."""
    import corner

    fig = corner.corner(result.samples, labels=result.param_names, quantiles=[0.16, 0.5, 0.84],
                        truths=result.map.theta, truth_color="tab:red", show_titles=True,
                        title_fmt=".4g", title_kwargs={"fontsize": 8}, label_kwargs={"fontsize": 8})
    return _save(fig, path)


def plot_fit(result, problem, out_dir) -> list[Path]:
    """All plots of a fit into ``out_dir``: one width/residual figure per scan, one corner."""
    out = Path(out_dir)
    files = [plot_tracks(p, out / f"fit_tracks_{p.get('scan', k)}.png")
             for k, p in enumerate(result.predictions)]
    files.append(plot_corner(result, out / "fit_corner.png"))
    return files
