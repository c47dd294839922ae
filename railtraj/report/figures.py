"""The report's plots, each a function returning PNG bytes.

Matplotlib's Agg canvas is used directly (no pyplot, no display, no global state), as in
:mod:`railtraj.report.votes`. Every plot is drawn against chainage along the reference run, so
the figures of one report line up.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle

from railtraj.qc import PairClouds
from railtraj.report.chainage import Chainage
from railtraj.report.clouds import cross_section, slab_width
from railtraj.report.sections import COLOURS, REFUSED, VERDICTS, PairPlace, Section

ENU = (("E", "tab:blue"), ("N", "tab:orange"), ("U", "tab:green"))


def _png(fig: Figure, dpi: int = 80) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def verdict_strip(sections: list[Section], places: list[PairPlace], chainage: Chainage) -> bytes:
    """One row per pair of runs: each section a coloured bar along the chainage."""
    rows = sorted({s.runs for s in sections})
    fig = _figure(9, 0.5 + 0.45 * len(rows))
    ax = fig.subplots()
    at = sorted({round(p.chainage, 1) for p in places})
    spacing = np.median(np.diff(at)) if len(at) > 1 else 10.0
    half = 0.5 * float(spacing if np.isfinite(spacing) and spacing > 0 else 10.0)
    for k, runs in enumerate(rows):
        for s in (s for s in sections if s.runs == runs):
            ax.broken_barh([(s.start - half, s.end - s.start + 2 * half)], (k - 0.35, 0.7),
                           facecolors=COLOURS[s.verdict], edgecolors="white", linewidth=0.5)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_ylim(-0.6, len(rows) - 0.4)
    ax.set_xlim(0, max(chainage.length, 1.0))
    ax.set_xlabel(f"chainage along {chainage.run_id} [m]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(handles=[Patch(color=COLOURS[v], label=v) for v in VERDICTS], ncol=4, fontsize=7,
              loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    return _png(fig)


def corrections(result, chainage: Chainage) -> bytes:
    """Per run, the correction applied (corrected - input) in E, N, U with its posterior 1-sigma."""
    runs = sorted(result.trajectories)
    fig = _figure(9, 0.6 + 2.0 * len(runs))
    axes = fig.subplots(len(runs), 1, sharex=True, squeeze=False)[:, 0]
    for ax, run_id in zip(axes, runs, strict=True):
        before, after = result.trajectories[run_id], result.corrected[run_id]
        s = chainage.of_trajectory(before)
        order = np.argsort(s, kind="stable")
        corr = (after.xyz - before.xyz)[order]
        sd = after.sd[order] if after.sd is not None else np.zeros_like(corr)
        for k, (lab, col) in enumerate(ENU):
            ax.plot(s[order], corr[:, k], color=col, lw=1, label=lab)
            ax.fill_between(s[order], corr[:, k] - sd[:, k], corr[:, k] + sd[:, k], color=col,
                            alpha=0.2, lw=0)
        _panel(ax, run_id, "correction [m]")
    return _chainage_figure(fig, axes, chainage.run_id)


def plan_map(result, places: list[PairPlace], clouds: list[PairClouds]) -> bytes:
    """Plan view: run a's tile of every pair coloured by its C2C median, before and after."""
    headers = {(r, t.path.name): t for r, run in result.survey.runs.items() for t in run.tiles}
    by_pair = {c.index: c for c in clouds}
    cells: dict[tuple[str, str], tuple[float, float]] = {}
    for p in places:
        c = by_pair.get(p.index)
        if c is None:
            continue
        key = (result.pairs[p.index].offset.run_a, p.tile_a)
        prev = cells.get(key, (0.0, 0.0))
        cells[key] = (max(prev[0], c.median_before), max(prev[1], c.median_after))
    vmax = max([v for pair in cells.values() for v in pair if np.isfinite(v)] + [0.01])
    norm = Normalize(0.0, vmax)
    xy = np.concatenate([t.xyz[:, :2] for t in result.trajectories.values()])
    dx, dy = np.ptp(xy, axis=0) + 1.0
    wide = dx >= 1.5 * dy  # a tunnel running east-west: the two maps one above the other
    fig = _figure(10, float(np.clip(10 * dy / dx, 1.5, 4.5)) * 2 + 1 if wide else 4.5)
    axes = fig.subplots(2, 1) if wide else fig.subplots(1, 2)
    for k, (ax, title) in enumerate(zip(axes, ("before", "after"), strict=True)):
        for traj in result.trajectories.values():
            ax.plot(traj.xyz[:, 0], traj.xyz[:, 1], color="0.6", lw=0.6)
        for key, values in cells.items():
            h = headers.get(key)
            if h is None or not np.isfinite(values[k]):
                continue
            ax.add_patch(Rectangle(tuple(h.mins[:2]), *(h.maxs[:2] - h.mins[:2]),
                                   facecolor=_cmap()(norm(values[k])), edgecolor="white", lw=0.4))
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"C2C median per tile, {title}", fontsize=9)
        if k == 1 or not wide:
            ax.set_xlabel("easting [m]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(useOffset=False, style="plain")
    for ax in axes:
        ax.set_ylabel("northing [m]", fontsize=8)
    from matplotlib.cm import ScalarMappable
    fig.colorbar(ScalarMappable(norm=norm, cmap=_cmap()), ax=axes, label="C2C median [m]",
                 shrink=0.8)
    return _png(fig)


def _cmap():
    from matplotlib import colormaps
    return colormaps["viridis"]


def c2c_histograms(clouds: list[PairClouds]) -> bytes:
    """Distribution of C2C distances over all pairs, before and after correction."""
    before = np.concatenate([c.c2c_before for c in clouds]) if clouds else np.zeros(0)
    after = np.concatenate([c.c2c_after for c in clouds]) if clouds else np.zeros(0)
    fig = _figure(9, 3)
    ax = fig.subplots()
    both = np.concatenate([before, after])
    top = max(np.percentile(both, 99) if len(both) else 0.1, 0.02)
    bins = np.linspace(0.0, top, 80)
    for d, lab, col in ((before, "before", "tab:red"), (after, "after", "tab:blue")):
        if len(d):
            ax.hist(d, bins=bins, histtype="step", lw=1.5, color=col,
                    label=f"{lab}: median {np.median(d) * 1000:.0f} mm, "
                          f"p95 {np.percentile(d, 95) * 1000:.0f} mm")
            ax.axvline(np.median(d), color=col, lw=0.8, ls="--")
    ax.set_xlabel("distance from run b's point to run a's nearest point [m]", fontsize=8)
    ax.set_ylabel("points", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return _png(fig)


def cross_sections(picks: list[tuple[str, PairClouds]], places: list[PairPlace], chainage: Chainage,
                   result) -> bytes:
    """Per picked pair, a slice across the track through both runs' points, before and after."""
    fig = _figure(10, 3.4 * len(picks))
    axes = fig.subplots(len(picks), 2, squeeze=False, sharey="row")
    for row, (label, c) in zip(axes, picks, strict=True):
        p = places[c.index]
        direction = chainage.direction(p.chainage)
        width = slab_width(c.a_before, p.xy, direction)
        o = result.pairs[c.index].offset
        views = (("before", c.a_before, c.b_before, c.median_before),
                 ("after", c.a_after, c.b_after, c.median_after))
        for ax, (title, a, b, med) in zip(row, views, strict=True):
            for pts, name, col in ((a, o.run_a, "tab:blue"), (b, o.run_b, "tab:red")):
                xs = cross_section(pts, p.xy, direction, width)
                ax.scatter(xs[:, 0], xs[:, 1], s=1.5, color=col, label=name, linewidths=0)
            where = f"{label}: {p.tile_a} ({p.runs}) at {p.chainage:.0f} m" * (title == "before")
            where += "\n"
            ax.set_title(f"{where}{title}: C2C median {med * 1000:.0f} mm", fontsize=8, loc="left")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel(f"across track, right of {chainage.run_id}'s direction [m] "
                          f"(slice {2 * width:.1f} m)", fontsize=7)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        row[0].set_ylabel("height [m]", fontsize=8)
        row[0].legend(fontsize=7, markerscale=5)
    fig.tight_layout()
    return _png(fig)


def truth_errors(errors: dict[str, dict[str, np.ndarray]], ref: str) -> bytes:
    """Horizontal and vertical position error against the truth along the chainage, per run."""
    fig = _figure(9, 4.6)
    axes = fig.subplots(2, 1, sharex=True)
    for k, run_id in enumerate(sorted(errors)):
        e = errors[run_id]
        col = f"C{k}"
        for ax, key in zip(axes, ("h", "v"), strict=True):
            ax.plot(e["chainage"], e[f"before_{key}"], color=col, lw=0.8, ls=":",
                    label=f"{run_id} before")
            ax.plot(e["chainage"], e[f"after_{key}"], color=col, lw=1.2, label=f"{run_id} after")
    axes[0].set_ylabel("horizontal error [m]", fontsize=8)
    axes[1].set_ylabel("|vertical error| [m]", fontsize=8)
    axes[1].set_xlabel(f"chainage along {ref} [m]", fontsize=8)
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7, ncol=len(errors))
    fig.tight_layout()
    return _png(fig)


def offsets_along(result, places: list[PairPlace], chainage: Chainage) -> bytes:
    """The matcher's offset of every tile pair (p_a = p_b + d) against chainage, one panel per
    pair of runs; hollow markers: weak or unresolved pairs (only partly used); refused pairs,
    whose numbers mean nothing, are left out."""
    runs = sorted({p.runs for p in places})
    fig = _figure(9, 0.6 + 1.9 * len(runs))
    axes = fig.subplots(len(runs), 1, sharex=True, squeeze=False)[:, 0]
    for ax, name in zip(axes, runs, strict=True):
        chain = [p for p in places if p.runs == name and p.verdict != REFUSED]
        s = np.array([p.chainage for p in chain])
        d = np.array([result.pairs[p.index].offset.d for p in chain]).reshape(-1, 3)
        ok = np.array([p.status == "ok" for p in chain], bool)
        for k, (lab, col) in enumerate(zip(("dx (E)", "dy (N)", "dz (U)"), ("C0", "C1", "C2"),
                                           strict=True)):
            ax.plot(s[ok], d[ok, k], "o", ms=4, color=col, label=lab)
            ax.plot(s[~ok], d[~ok, k], "o", ms=4, mfc="none", color=col)
        _panel(ax, name, "offset [m]")
    return _chainage_figure(fig, axes, chainage.run_id)


def _panel(ax, title: str, ylabel: str) -> None:
    """One panel of a stack of plots against chainage: title left, light grid, small ticks."""
    ax.set_title(title, fontsize=9, loc="left")
    ax.set_ylabel(ylabel, fontsize=8)
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)


def _chainage_figure(fig, axes, run_id: str) -> bytes:
    """The stack finished (legend on top, chainage axis below) as PNG bytes."""
    axes[0].legend(ncol=3, fontsize=7, loc="upper right")
    axes[-1].set_xlabel(f"chainage along {run_id} [m]", fontsize=8)
    fig.tight_layout()
    return _png(fig)
