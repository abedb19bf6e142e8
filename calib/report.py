"""Plots of comparisons and diagnoses, and the one-file HTML report.

Every figure is drawn with matplotlib (Agg) and either saved as PNG or embedded in the
report as a base64 data URI, so the report is a single self-contained file that opens
in any browser without network access.
"""
from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calib.fileio import atomic_write_bytes, atomic_write_text  # noqa: E402

#: Model colours, in order of the comparison (best first). Data is drawn in grey.
COLOURS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
DATA_COLOUR = "#7f7f7f"


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def fig_tracks(scan, fits, max_tracks: int = 12):
    """Data and every model's width along each track (top), residuals (bottom), in mm.

    ``scan``: :class:`fit.data.ScanData`; ``fits``: :class:`fit.compare.ModelFit` (their
    ``pred_mm``/``resid_mm`` are in the scan's valid-sample order)."""
    track, s_all = scan.track_valid, scan.s_valid_mm
    tids = list(dict.fromkeys(track.tolist()))[:max_tracks]
    ncol = min(3, len(tids))
    nrow = int(np.ceil(len(tids) / ncol))
    fig, axes = plt.subplots(2 * nrow, ncol, figsize=(5 * ncol, 3.2 * nrow), squeeze=False,
                             gridspec_kw={"height_ratios": [2, 1] * nrow})
    for i, tid in enumerate(tids):
        r, c = 2 * (i // ncol), i % ncol
        ax, axr = axes[r, c], axes[r + 1, c]
        m = track == tid
        s = s_all[m]
        ax.plot(s, scan.y_mm[m], ".", ms=2, color=DATA_COLOUR, label="measured")
        for j, f in enumerate(fits):
            col = COLOURS[j % len(COLOURS)]
            ax.plot(s, f.pred_mm[m], "-", lw=1.2, color=col, label=f.spec)
            axr.plot(s, 1000 * f.resid_mm[m], "-", lw=0.8, color=col)
        axr.axhline(0, color="k", lw=0.5)
        ax.set_title(f"track {tid}", fontsize=9)
        ax.set_ylabel("width (mm)")
        axr.set_ylabel("resid (um)")
        axr.set_xlabel("s (mm)")
        if i == 0:
            ax.legend(fontsize=7)
    for k in range(len(tids), nrow * ncol):
        axes[2 * (k // ncol), k % ncol].axis("off")
        axes[2 * (k // ncol) + 1, k % ncol].axis("off")
    fig.tight_layout()
    return fig


def plot_tracks(scan, fits, out_dir) -> Path:
    path = Path(out_dir) / "compare_tracks.png"
    atomic_write_bytes(path, _png(fig_tracks(scan, fits)))
    return path


def fig_covariate(diag, score):
    """Residual (um) against one covariate with its binned-mean curve; less each track's
    mean where the diagnosis scored within tracks (widths measured from a picture)."""
    from fit.covariates import COVARIATES, track_demeaned
    fig, ax = plt.subplots(figsize=(5, 3.2))
    x = diag.cov[score.name]
    within = diag.within_tracks and diag.track is not None
    r = track_demeaned(diag.base.resid_mm, diag.track) if within else diag.base.resid_mm
    ax.plot(x, 1000 * r, ".", ms=2, color=DATA_COLOUR, alpha=0.5)
    if score.bin_centres is not None and len(score.bin_centres):
        ax.plot(score.bin_centres, 1000 * np.asarray(score.bin_means), "o-", color=COLOURS[0])
    ax.axhline(0, color="k", lw=0.5)
    unit = COVARIATES.get(score.name, ("", ""))[0]
    ax.set_xlabel(f"{score.name} ({unit})")
    ax.set_ylabel(f"residual of {diag.model}{' less its track mean' if within else ''} (um)")
    ax.set_title(f"{score.name}: score {score.score:.2f}", fontsize=9)
    fig.tight_layout()
    return fig


def plot_covariates(diag, out_dir, top: int = 4) -> list[Path]:
    out = []
    for s in diag.covariates[:top]:
        p = Path(out_dir) / f"residual_vs_{s.name}.png"
        atomic_write_bytes(p, _png(fig_covariate(diag, s)))
        out.append(p)
    return out


def fig_candidates(diag):
    """Bar chart: drop in BIC per candidate effect (log scale), best first."""
    cs = [c for c in diag.candidates if np.isfinite(c.delta_bic)][:10]
    fig, ax = plt.subplots(figsize=(6, 0.35 * len(cs) + 1))
    vals = [max(c.delta_bic, 0.1) for c in cs]
    ax.barh([c.effect for c in cs][::-1], vals[::-1],
            color=[COLOURS[1] if c.delta_bic > 10 else DATA_COLOUR for c in cs][::-1])
    ax.set_xscale("log")
    ax.set_xlabel("drop in BIC when added (blue: supported)")
    fig.tight_layout()
    return fig


def fig_corner(fit):
    """Corner plot of a full fit's posterior draws (:class:`fit.compare.ModelFit` with ``full``)."""
    import corner
    fig = corner.corner(fit.full.samples, labels=list(fit.full.param_names),
                        quantiles=[0.16, 0.5, 0.84], show_titles=True,
                        title_fmt=".3g", title_kwargs={"fontsize": 8})
    return fig


def _img(data: bytes, alt: str, width: str = "100%", mime: str = "image/png") -> str:
    b64 = base64.b64encode(data).decode("ascii")
    return f'<img alt="{html.escape(alt)}" style="max-width:{width}" src="data:{mime};base64,{b64}">'


def image_file(path, max_px: int = 1400) -> bytes:
    """A JPEG (quality 85) of a photo or scan, at most ``max_px`` on its long side: a
    12 MP photo embedded as PNG made a 6 MB report; as JPEG it is ~0.3 MB."""
    from PIL import Image

    from calib.errors import UserError

    buf = io.BytesIO()
    try:
        with Image.open(path) as im:
            im.thumbnail((max_px, max_px))
            im.convert("RGB").save(buf, format="JPEG", quality=85, optimize=True)
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        # PIL's UnidentifiedImageError and a truncated file's "Truncated File Read" are OSErrors
        raise UserError(f"image {path} cannot be read (corrupt, truncated or not an image: {exc})") from None
    return buf.getvalue()


CSS = """body{font-family:sans-serif;margin:24px;max-width:1150px;color:#222}
h1{font-size:22px}h2{font-size:18px;border-bottom:1px solid #ccc;margin-top:28px}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#eee}td:first-child{text-align:left}.verdict{background:#eef6ff;border-left:5px solid #1f77b4;
padding:10px 14px;font-size:15px}.grid{display:flex;flex-wrap:wrap;gap:8px}.grid img{max-width:48%}
code{background:#f4f4f4;padding:1px 4px}.quality{padding:8px 14px;margin:10px 0}
.quality.ok{background:#eefbee;border-left:5px solid #2ca02c}.quality.bad{background:#fdecea;border-left:5px solid #d62728}"""


def build_report(title: str, obs=None, comparison=None, diagnosis=None, compare_doc=None,
                 diagnose_doc=None, fit_doc=None, scan=None, overlay=None) -> str:
    """The HTML text of the report from whatever exists (every part optional)."""
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if diagnose_doc is not None:
        parts.append(f"<h2>Verdict</h2><p class='verdict'>{html.escape(diagnose_doc.get('verdict', ''))}</p>")
        if diagnose_doc.get("command"):
            parts.append(f"<p>Next: <code>{html.escape(diagnose_doc['command'])}</code></p>")
    if scan or overlay:
        parts.append("<h2>Scan and measurement overlay</h2><div class='grid'>")
        for p, alt in ((scan, "scan"), (overlay, "QA overlay")):
            if p:
                parts.append(_img(image_file(p), alt, "48%", "image/jpeg"))
        parts.append("</div>")
    if compare_doc is not None:
        parts.append("<h2>Model comparison</h2>" + _compare_table(compare_doc["models"]))
    if obs is not None and comparison is not None:
        parts.append("<h2>Data vs models, track by track</h2>")
        parts.append(_img(_png(fig_tracks(obs, comparison.fits)), "data vs models"))
    if diagnose_doc is not None:
        parts.append("<h2>Candidate effects</h2>" + _candidate_table(diagnose_doc["candidates"]))
        parts.append("<h2>Residual structure</h2>" + _cov_table(diagnose_doc["covariates"][:8]))
    if diagnosis is not None:
        parts.append(_img(_png(fig_candidates(diagnosis)), "candidates", "60%"))
        parts.append("<div class='grid'>" + "".join(
            _img(_png(fig_covariate(diagnosis, s)), s.name, "48%") for s in diagnosis.covariates[:4])
            + "</div>")
    if comparison is not None:
        full = [f for f in comparison.fits if f.full is not None]
        if full:
            parts.append("<h2>Posterior (corner plots)</h2><div class='grid'>")
            parts += [f"<div><p>{html.escape(f.spec)}</p>{_img(_png(fig_corner(f)), f.spec)}</div>"
                      for f in full[:3]]
            parts.append("</div>")
    if fit_doc is not None:
        parts.append(_fit_section(fit_doc))
    parts.append("</body></html>")
    return "\n".join(parts)


def _fmt(x, fmt="{:.1f}"):
    return "-" if x is None or (isinstance(x, float) and x != x) else fmt.format(x)


def _compare_table(rows) -> str:
    h = ("model", "RMS (um)", "chi2_nu", "BIC", "dBIC", "elpd_loo", "se", "d elpd", "d se", "parameters")
    out = ["<table><tr>" + "".join(f"<th>{x}</th>" for x in h) + "</tr>"]
    for r in rows:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in r["params"].items() if v is not None)
        cells = (r["model"], _fmt(1000 * r["rms_mm"]), _fmt(r["chi2_nu"], "{:.2f}"), _fmt(r["bic"]),
                 _fmt(r["delta_bic"]), _fmt(r.get("elpd_loo")), _fmt(r.get("elpd_loo_se")),
                 _fmt(r.get("delta_elpd_loo")), _fmt(r.get("delta_elpd_loo_se")), ps)
        out.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
    return "".join(out) + "</table>"


def _candidate_table(cands) -> str:
    out = ["<table><tr><th>effect added</th><th>drop in BIC</th>"
           "<th>RMS after (um)</th><th>chi2_nu after</th></tr>"]
    for c in cands:
        out.append(f"<tr><td>{html.escape(c['effect'])}{' (yours)' if c.get('user') else ''}</td>"
                   f"<td>{_fmt(c['delta_bic'])}</td>"
                   f"<td>{_fmt(None if c['rms_mm_after'] is None else 1000 * c['rms_mm_after'])}</td>"
                   f"<td>{_fmt(c.get('chi2_nu_after'), '{:.2f}')}</td></tr>")
    return "".join(out) + "</table>"


def _cov_table(covs) -> str:
    out = ["<table><tr><th>covariate</th><th>score</th><th>R^2</th><th>p</th></tr>"]
    for c in covs:
        out.append(f"<tr><td>{html.escape(c['name'])}</td><td>{_fmt(c['score'], '{:.3f}')}</td>"
                   f"<td>{_fmt(c.get('r2'), '{:.3f}')}</td><td>{_fmt(c.get('p_value'), '{:.3g}')}</td></tr>")
    return "".join(out) + "</table>"


def _fit_section(doc) -> str:
    """Parameters with intervals and sampler health, then the lines to paste into firmware."""
    d = doc.get("diagnostics", {})
    ok = "converged" if doc.get("converged") else "NOT converged: " + str(d.get("warning", d.get("stop_reason", "")))
    out = [f"<h2>Fit: {html.escape(str(doc.get('model', '')))}</h2>",
           f"<p>{html.escape(ok)}; {d.get('n_steps', '-')} steps x {d.get('n_walkers', '-')} walkers x "
           f"{d.get('n_ensembles', '-')} ensembles, acceptance {_fmt(d.get('acceptance_fraction'), '{:.2f}')}</p>",
           "<table><tr><th>parameter</th><th>median</th><th>68 % interval</th><th>95 % interval</th>"
           "<th>R-hat</th><th>ESS</th></tr>"]
    for name, p in doc.get("params", {}).items():
        lo68, hi68 = p.get("ci68", [None, None])
        lo95, hi95 = p.get("ci95", [None, None])
        out.append(f"<tr><td>{html.escape(name)}</td><td>{_fmt(p.get('median'), '{:.5g}')}</td>"
                   f"<td>{_fmt(lo68, '{:.5g}')} - {_fmt(hi68, '{:.5g}')}</td>"
                   f"<td>{_fmt(lo95, '{:.5g}')} - {_fmt(hi95, '{:.5g}')}</td>"
                   f"<td>{_fmt(p.get('rhat'), '{:.4f}')}</td><td>{_fmt(p.get('ess'), '{:.0f}')}</td></tr>")
    out.append("</table>")
    from fit.trust import CHI2_NU_MAX, assess

    v = assess(doc, chi2_max=(doc.get("trust") or {}).get("checks", {}).get("chi2_nu_max", CHI2_NU_MAX))
    lines = v.lines()
    cls = "ok" if v.trustworthy else "bad"
    out.append(f"<div class='quality {cls}'><p><b>{html.escape(lines[0])}</b></p><ul>"
               + "".join(f"<li>{html.escape(x.strip(' -'))}</li>" for x in lines[1:]) + "</ul></div>")
    fw = doc.get("derived", {}).get("firmware", {})
    if fw and not v.trustworthy:
        out.append("<p>No firmware lines: the values above are not trustworthy.</p>")
    elif fw:
        out.append("<p>Firmware:</p><pre>" + html.escape("\n".join(
            f"{k:15s} {v}" for k, v in fw.items() if "\n" not in v)) + "</pre>")
    return "\n".join(out)


def write_report(path, text: str) -> Path:
    return atomic_write_text(path, text)
