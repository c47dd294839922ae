"""OUT/report.html: the QC report a surveyor reads, one self-contained file (plots inlined).

Sections: summary figures, tile-pair offsets along the survey, corrections applied to each run,
tie residuals before/after, and the table of tile pairs with their status.
"""

from __future__ import annotations

import base64
import html
import io
import json
from typing import Any

import numpy as np

from railtraj.io.atomic import atomic_write


def _figure_to_img(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _plots(result) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    shown = [o for o in result.offsets if np.isfinite(o.d).all()]
    if shown:
        fig, ax = plt.subplots(figsize=(8, 3))
        t = np.arange(len(shown))
        d = np.array([o.d for o in shown])
        ok = np.array([o.ok for o in shown])
        for k, (lab, col) in enumerate(zip("xyz", ("C0", "C1", "C2"), strict=True)):
            ax.plot(t[ok], d[ok, k], "o", ms=4, color=col, label=f"d{lab} (ok)")
            ax.plot(t[~ok], d[~ok, k], "o", ms=4, mfc="none", color=col, label=f"d{lab} (not ok)")
        ax.set_xlabel("tile pair (offsets.csv order)")
        ax.set_ylabel("offset run_b -> run_a [m]")
        ax.legend(ncol=3, fontsize=7)
        ax.grid(alpha=0.3)
        out.append(("Tile-pair offsets (hollow: degenerate, ambiguous or refused)", _figure_to_img(fig)))
    runs = sorted(result.trajectories)
    fig, axes = plt.subplots(len(runs), 1, figsize=(8, 2.2 * len(runs)), sharex=False, squeeze=False)
    for ax, run_id in zip(axes[:, 0], runs, strict=True):
        traj, corr_traj = result.trajectories[run_id], result.corrected[run_id]
        t = traj.time - traj.time[0]
        corr = corr_traj.xyz - traj.xyz
        sd = corr_traj.sd if corr_traj.sd is not None else np.zeros_like(corr)
        for k, (lab, col) in enumerate(zip("ENU", ("C0", "C1", "C2"), strict=True)):
            ax.plot(t, corr[:, k], color=col, lw=1, label=lab)
            ax.fill_between(t, corr[:, k] - sd[:, k], corr[:, k] + sd[:, k], color=col, alpha=0.2, lw=0)
        ax.set_title(run_id, fontsize=9)
        ax.set_ylabel("correction [m]")
        ax.grid(alpha=0.3)
        ax.legend(ncol=3, fontsize=7)
    axes[-1, 0].set_xlabel("time since run start [s]")
    fig.tight_layout()
    out.append(("Correction applied to each run (band: posterior 1-sigma)", _figure_to_img(fig)))
    return out


def _table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "<p>none</p>"
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in r.values()) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "" if not np.isfinite(v) else f"{v:.4f}"
    return str(v)


def _adjustment_section(metrics: dict[str, Any]) -> str:
    """What the optimizer used and rejected, where it was unconstrained, control residuals."""
    adj, control = metrics.get("adjustment") or {}, metrics.get("control") or []
    parts = []
    if adj.get("observations"):
        rows = [{"observations": k, **v} for k, v in adj["observations"].items()]
        parts.append(f"<h3>Observations</h3>{_table(rows)}<p>{adj.get('gnc_iterations', 0)} robust iterations "
                     f"(GNC, truncated least squares), {adj.get('knots', 0)} knots.</p>")
    if adj.get("alongtrack"):
        rows = [{k: v for k, v in r.items() if k != "candidate_shifts_m"} for r in adj["alongtrack"]]
        fixed = sum(r["status"] == "ok" for r in rows)
        parts.append(f"<h3>Along the track: {fixed} of {len(rows)} tile pairs with alias candidates fixed</h3>"
                     f"<p>shift: the alias chosen, relative to the matcher's own offset (m); margin: how "
                     f"much better it fits the chain than the runner-up (chi-square; fixed from 16)</p>"
                     f"{_table(rows)}")
    if adj.get("rejected"):
        parts.append(f"<h3>Rejected observations (first {len(adj['rejected'])})</h3>{_table(adj['rejected'])}")
    if adj.get("under_constrained"):
        parts.append(f"<h3>Stretches with no observation</h3>{_table(adj['under_constrained'])}")
    if control:
        rows = [{k: v for k, v in c.items() if not isinstance(v, list)} for c in control]
        parts.append(f"<h3>Control points: residual before and after [m]</h3>{_table(rows)}")
    return "<h2>Global adjustment</h2>" + "".join(parts) if parts else ""


def write_report(path, result, metrics: dict[str, Any]) -> None:
    """Write the HTML report for a pipeline result and its metrics."""
    qc = metrics["qc"]
    summary = [{"figure": name, **{k: qc[key].get(k) for k in ("n", "median", "rms", "p95", "max")}}
               for name, key in (("tie residual before [m]", "tie_residual_before_m"),
                                 ("tie residual after [m]", "tie_residual_after_m"),
                                 ("C2C before [m]", "c2c_before_m"), ("C2C after [m]", "c2c_after_m"))]
    pairs = [{"run_a": o.run_a, "run_b": o.run_b, "tile_a": o.tile_a, "tile_b": o.tile_b,
              "dx": float(o.d[0]), "dy": float(o.d[1]), "dz": float(o.d[2]), "sd_x": float(o.sd[0]),
              "sd_y": float(o.sd[1]), "sd_z": float(o.sd[2]), "inliers": o.inliers, "status": o.status}
             for o in result.offsets]
    plots = "".join(f"<h2>{html.escape(t)}</h2>{img}" for t, img in _plots(result))
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in metrics.get("notes", []))
    adjustment = _adjustment_section(metrics)
    truth = ""
    if "truth" in metrics:
        truth = f"<h2>Against the simulator's truth</h2><pre>{html.escape(json.dumps(metrics['truth'], indent=1)[:20000])}</pre>"
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>railtraj QC report</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:70em}}table{{border-collapse:collapse;font-size:90%}}
td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>railtraj QC report</h1>
<p>Survey <code>{html.escape(str(result.survey.root))}</code>, pipeline <b>{html.escape(result.options.mode)}</b>:
{metrics['counts']['runs']} runs, {metrics['counts']['tiles']} tiles, {metrics['counts']['tile_pairs']} tile pairs
({html.escape(json.dumps(metrics['counts']['tile_pairs_by_status']))}), {metrics['counts']['ties']} ties,
{metrics['counts']['anchors']} anchors.</p>
<ul>{notes}</ul>
<h2>Summary</h2>{_table(summary)}
{plots}{adjustment}{truth}
<h2>Tile pairs</h2>{_table(pairs)}
<h2>Timings [s]</h2><pre>{html.escape(json.dumps(metrics['seconds'], indent=1))}</pre>
</body></html>"""
    with atomic_write(path) as fh:
        fh.write(doc)
