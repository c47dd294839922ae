"""The rows of the report's tables, built from the pipeline result and metrics.json.

Each function returns a list of dicts (column header -> value) for
:func:`railtraj.report.tables.table`; headers carry the unit, which also sets the decimals.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from railtraj.qc import PairClouds
from railtraj.report.sections import COLOURS, PairPlace, Section, pair_reason
from railtraj.report.tables import Badge, mm

NAN = float("nan")


def qc_rows(qc: dict[str, Any]) -> list[dict[str, Any]]:
    """Tie residuals and C2C before and after: count, median, RMS, p95, max."""
    rows = []
    for name, key in (("tie residual before", "tie_residual_before_m"),
                      ("tie residual after", "tie_residual_after_m"),
                      ("C2C before", "c2c_before_m"), ("C2C after", "c2c_after_m")):
        stats = qc.get(key, {})
        rows.append({"figure": name, "n": stats.get("n"),
                     **{f"{k} [mm]": mm(stats.get(k)) for k in ("median", "rms", "p95", "max")}})
    return rows


def section_rows(secs: list[Section], clouds: dict[int, PairClouds]) -> list[dict[str, Any]]:
    """One row per tunnel section: where, how many pairs, verdict, worst C2C before/after."""
    rows = []
    for s in secs:
        before = [clouds[k].median_before for k in s.pairs if k in clouds]
        after = [clouds[k].median_after for k in s.pairs if k in clouds]
        rows.append({"runs": s.runs, "from [m]": round(s.start), "to [m]": round(s.end),
                     "tile pairs": len(s.pairs), "verdict": Badge(s.verdict, COLOURS[s.verdict]),
                     "C2C median before [mm] (worst pair)": _worst(before),
                     "C2C median after [mm] (worst pair)": _worst(after)})
    return rows


def _worst(values: list[float]) -> float:
    return mm(np.nanmax(values)) if values and np.isfinite(values).any() else NAN


def correction_rows(result) -> list[dict[str, Any]]:
    """Per run: the largest correction and the median posterior sd, E/N/U."""
    rows = []
    for run_id in sorted(result.trajectories):
        corr = result.corrected[run_id].xyz - result.trajectories[run_id].xyz
        sd = result.corrected[run_id].sd
        row: dict[str, Any] = {"run": run_id}
        row.update({f"max |{a}| [mm]": mm(np.abs(corr[:, k]).max()) for k, a in enumerate("ENU")})
        row.update({f"median sd {a} [mm]": mm(np.median(sd[:, k])) if sd is not None else NAN
                    for k, a in enumerate("ENU")})
        rows.append(row)
    return rows


def problem_rows(result, places: list[PairPlace], alongtrack: list[dict]) -> list[dict[str, Any]]:
    """Every pair that is not ``ok``, with the reason in words, by runs and chainage."""
    along = {r["pair"]: r for r in alongtrack}  # by position: a large tile pair is matched in parts
    rows = []
    for p in places:
        o = result.pairs[p.index].offset
        if o.status == "ok":
            continue
        rows.append({"runs": p.runs, "tile a": o.tile_a, "tile b": o.tile_b,
                     "chainage [m]": round(p.chainage),
                     "status": Badge(o.status, COLOURS[p.verdict]),
                     "reason": pair_reason(o, along.get(p.index))})
    return sorted(rows, key=lambda r: (r["runs"], r["chainage [m]"]))


def control_rows(control: list[dict]) -> list[dict[str, Any]]:
    """Residual surveyed minus seen per control observation, E/N/U before and after."""
    rows = []
    for c in control:
        row: dict[str, Any] = {"point": c["id"], "run": c["run_id"], "source": c.get("source", "")}
        row.update({f"{a} before [mm]": mm(c["before_m"][k]) for k, a in enumerate("ENU")})
        row.update({f"{a} after [mm]": mm(c["after_m"][k]) for k, a in enumerate("ENU")})
        row["horizontal before [mm]"] = mm(c.get("horizontal_before"))
        row["horizontal after [mm]"] = mm(c.get("horizontal_after"))
        rows.append(row)
    return rows


def truth_rows(truth: dict[str, Any], part: str) -> list[dict[str, Any]]:
    """Errors against the truth, before and after: per run (``runs``) or between runs
    (``consistency``)."""
    rows = []
    for name in sorted(truth["before"].get(part, {})):
        row: dict[str, Any] = {"run" if part == "runs" else "runs": name}
        for k in ("rms_h", "rms_v", "max_h"):
            for when in ("before", "after"):
                row[f"{k} {when} [mm]"] = mm(truth[when].get(part, {}).get(name, {}).get(k))
        rows.append(row)
    return rows


def offset_truth_rows(truth: dict[str, Any]) -> list[dict[str, Any]]:
    """Errors of the ``ok`` tile-pair offsets against the true offsets."""
    off = truth.get("tile_offsets") or {}
    if not off:
        return []
    row: dict[str, Any] = {"ok pairs": off.get("ok_pairs", 0)}
    rms, top = off.get("rms_m") or [NAN] * 3, off.get("max_abs_m") or [NAN] * 3
    row.update({f"RMS {a} [mm]": mm(v) for a, v in zip("ENU", rms, strict=False)})
    row.update({f"max |{a}| [mm]": mm(v) for a, v in zip("ENU", top, strict=False)})
    row["share within 1 cm"] = off.get("within_1cm")
    return [row]


def pair_rows(result, places: list[PairPlace],
              clouds: dict[int, PairClouds]) -> list[dict[str, Any]]:
    """Every tile pair: offset, sd, inliers, status and C2C median before/after."""
    rows = []
    for p in places:
        o = result.pairs[p.index].offset
        c = clouds.get(p.index)
        row: dict[str, Any] = {"runs": p.runs, "tile a": p.tile_a, "tile b": p.tile_b,
                               "chainage [m]": round(p.chainage),
                               "status": Badge(p.status, COLOURS[p.verdict])}
        row.update({f"d{a} [m]": float(o.d[k]) for k, a in enumerate("xyz")})
        row.update({f"sd {a} [mm]": mm(np.sqrt(o.cov[k, k])) for k, a in enumerate("xyz")})
        row["inliers"] = o.inliers
        row["C2C before [mm]"] = mm(c.median_before) if c else NAN
        row["C2C after [mm]"] = mm(c.median_after) if c else NAN
        rows.append(row)
    return rows
