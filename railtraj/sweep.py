"""The summary of a comparative sweep (``railtraj -m ...``): one row per job.

After the last job, :class:`railtraj.cli.SweepSummary` (a Hydra callback) calls
:func:`write_sweep_summary`, which reads every job's ``metrics.json`` and writes to the sweep
folder:

* ``summary.csv``: machine-readable, SI units (metres, seconds), ``nan`` where a figure is missing;
* ``summary.md``: the same table for people (millimetres), best accuracy first;
* ``summary.png``: accuracy against wall time, one labelled point per job: RMS horizontal
  error against the truth when every job has one (``truth_dir=``), else the median C2C distance
  between runs after correction.

A job that wrote no ``metrics.json`` (bad input, a crash) is a row with status ``failed``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from railtraj.io.atomic import atomic_write

#: the columns of summary.csv, in order
COLUMNS = ("job", "overrides", "status", "tile_pairs", "tile_pairs_ok", "c2c_median_before_m",
           "c2c_median_after_m", "tie_rms_after_m", "truth_rms_h_before_m", "truth_rms_h_after_m",
           "truth_rms_v_after_m", "truth_interrun_rms_h_after_m", "wall_time_s")


@dataclass
class Job:
    """One job of the sweep: its folder and, when the callback measured it, its wall time."""

    folder: Path
    overrides: str
    wall_time_s: float = math.nan


def job_row(job: Job) -> dict[str, Any]:
    """The summary row of one job, from its metrics.json."""
    row: dict[str, Any] = dict.fromkeys(COLUMNS, math.nan)
    row.update(job=job.folder.name, overrides=job.overrides or "(defaults)",
               wall_time_s=job.wall_time_s)
    path = job.folder / "metrics.json"
    if not path.is_file():
        row["status"] = "failed"
        return row
    m = json.loads(path.read_text(encoding="utf-8"))
    counts, qc = m.get("counts", {}), m.get("qc", {})
    row.update(status="ok", tile_pairs=counts.get("tile_pairs", 0),
               tile_pairs_ok=counts.get("tile_pairs_by_status", {}).get("ok", 0),
               c2c_median_before_m=_num(qc.get("c2c_before_m", {}).get("median")),
               c2c_median_after_m=_num(qc.get("c2c_after_m", {}).get("median")),
               tie_rms_after_m=_num(qc.get("tie_residual_after_m", {}).get("rms")))
    truth = m.get("truth")
    if truth:
        before, after = truth["before"].get("overall", {}), truth["after"].get("overall", {})
        pairs = [p.get("rms_h") for p in truth["after"].get("consistency", {}).values()]
        row.update(truth_rms_h_before_m=_num(before.get("rms_h")),
                   truth_rms_h_after_m=_num(after.get("rms_h")),
                   truth_rms_v_after_m=_num(after.get("rms_v")),
                   truth_interrun_rms_h_after_m=max((_num(p) for p in pairs), default=math.nan))
    if math.isnan(row["wall_time_s"]):  # not measured by the callback: the job's own stage clocks
        clocks = m.get("seconds", {}).values()
        row["wall_time_s"] = sum(v for v in clocks if isinstance(v, (int, float)))
    return row


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) else math.nan


def find_jobs(sweep_dir: Path) -> list[Job]:
    """The job folders of a sweep (those with Hydra's ``.hydra/`` record), by name."""
    return [Job(p, p.name) for p in sorted(sweep_dir.iterdir()) if (p / ".hydra").is_dir()]


def write_sweep_summary(sweep_dir: Path, jobs: list[Job] | None = None) -> list[dict[str, Any]]:
    """Write summary.csv, summary.md and summary.png into ``sweep_dir``; return the rows."""
    jobs = jobs if jobs else find_jobs(sweep_dir)
    rows = [job_row(j) for j in jobs]
    with atomic_write(sweep_dir / "summary.csv") as fh:
        fh.write(",".join(COLUMNS) + "\n")
        for r in rows:
            fh.write(",".join(_csv(r[c]) for c in COLUMNS) + "\n")
    with atomic_write(sweep_dir / "summary.md") as fh:
        fh.write(markdown(rows))
    _plot(rows, sweep_dir / "summary.png")
    return rows


def _csv(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6f}"
    text = str(v)
    return '"' + text.replace('"', '""') + '"' if ("," in text or '"' in text) else text


def _accuracy(rows: list[dict[str, Any]]) -> tuple[str, str]:
    """The accuracy figure every finished job has: truth if all have it, else C2C after."""
    done = [r for r in rows if r["status"] == "ok"]
    if done and all(not math.isnan(r["truth_rms_h_after_m"]) for r in done):
        return "truth_rms_h_after_m", "RMS horizontal error vs truth"
    return "c2c_median_after_m", "C2C median between runs after correction"


def markdown(rows: list[dict[str, Any]]) -> str:
    """summary.md: one row per job, most accurate first, figures in millimetres (truth columns
    only when some job has a truth)."""
    key, label = _accuracy(rows)
    ordered = sorted(rows, key=lambda r: (math.isnan(r[key]), r[key]))
    truth = any(not math.isnan(r["truth_rms_h_after_m"]) for r in rows)
    cols = ["overrides", "status", "tile pairs ok", "C2C median before -> after [mm]",
            "tie RMS after [mm]"]
    if truth:
        cols += ["truth RMS h before -> after [mm]", "truth RMS v after [mm]",
                 "worst inter-run RMS h [mm]"]
    cols.append("wall time [s]")
    lines = [f"# Sweep summary ({len(rows)} jobs, sorted by {label})", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in ordered:
        cells = [f"`{r['overrides']}`", r["status"],
                 f"{_int(r['tile_pairs_ok'])} / {_int(r['tile_pairs'])}",
                 f"{_mm(r['c2c_median_before_m'])} -> {_mm(r['c2c_median_after_m'])}",
                 _mm(r["tie_rms_after_m"])]
        if truth:
            cells += [f"{_mm(r['truth_rms_h_before_m'])} -> {_mm(r['truth_rms_h_after_m'])}",
                      _mm(r["truth_rms_v_after_m"]), _mm(r["truth_interrun_rms_h_after_m"])]
        cells.append(_sec(r["wall_time_s"]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _mm(v: float) -> str:
    return "-" if math.isnan(v) else f"{v * 1000:.1f}"


def _int(v: Any) -> str:
    return "-" if isinstance(v, float) and math.isnan(v) else str(v)


def _sec(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.1f}"


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Accuracy against wall time, one labelled point per finished job."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    key, label = _accuracy(rows)
    fig = Figure(figsize=(7, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    done = [r for r in rows if r["status"] == "ok" and not math.isnan(r[key])
            and not math.isnan(r["wall_time_s"])]
    for r in done:
        ax.scatter(r["wall_time_s"], r[key] * 1000, color="tab:blue", s=25)
        ax.annotate(r["overrides"], (r["wall_time_s"], r[key] * 1000), fontsize=7, xytext=(4, 3),
                    textcoords="offset points")
    if not done:
        ax.text(0.5, 0.5, "no finished job", ha="center", va="center", transform=ax.transAxes)
    elif min(r[key] for r in done) > 0:
        from matplotlib.ticker import ScalarFormatter

        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.margins(x=0.15, y=0.1)
    ax.set_xlabel("wall time per job [s]")
    ax.set_ylabel(f"{label} [mm]")
    ax.set_title(f"Sweep: {len(done)} of {len(rows)} jobs", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    with atomic_write(path, mode="wb") as fh:
        fh.write(buf.getvalue())
