"""OUT/report.html: the QC report a surveyor reads, one self-contained file (plots inlined).

Order of the page, most important first: a summary with a verdict per tunnel section, the
correction applied to each run, inter-run misalignment before and after (plan view, C2C
histograms, cross-sections), the pairs that were refused or left ambiguous and why, control
residuals, errors against the truth (simulated surveys only), then the details (all tile
pairs, the adjustment, configuration and timings) collapsed.
Plots are made by :mod:`railtraj.report.figures`, verdicts by :mod:`railtraj.report.sections`.
"""

from __future__ import annotations

import base64
import html
import logging
from pathlib import Path
from typing import Any

import numpy as np

from railtraj.io.atomic import atomic_write
from railtraj.report import figures
from railtraj.report.chainage import Chainage, reference_run
from railtraj.report.clouds import pair_clouds, pick_pairs
from railtraj.report.sections import COLOURS, VERDICTS, pair_reason, place_pairs, sections
from railtraj.report.tables import Badge, key_values, mm, table

log = logging.getLogger(__name__)

STYLE = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:72em;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:85%;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 6px;
text-align:right}th{background:#eee}img{max-width:100%}h2{border-bottom:2px solid #ddd;margin-top:1.6em}
.badge{color:#fff;padding:1px 6px;border-radius:3px;white-space:nowrap}.cards{display:flex;gap:1em;
flex-wrap:wrap}.card{border:1px solid #ccc;border-radius:6px;padding:.5em 1em;min-width:9em}
.card b{font-size:160%;display:block}details{margin:.6em 0}summary{cursor:pointer;font-weight:bold}
table.left td{text-align:left}.note{background:#fff4d6;padding:.3em .6em;border-left:4px solid #ffbf00}p.none{color:#888}"""


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def write_report(path, result, metrics: dict[str, Any], truth_dir: Path | None = None) -> None:
    """Write the HTML report for a pipeline result and its metrics (and the truth, if simulated)."""
    chainage = Chainage(result.trajectories[reference_run(sorted(result.trajectories),
                                                          result.options.reference_run)])
    places = place_pairs(result, chainage)
    secs = sections(places)
    clouds = pair_clouds(result)
    parts = [_header(result, metrics), _summary(result, metrics, places, secs, clouds, chainage),
             _corrections(result, chainage), _misalignment(result, metrics, places, clouds, chainage),
             _problem_pairs(result, metrics, places), _control(metrics),
             _truth(result, metrics, truth_dir, chainage), _details(result, metrics, places, clouds)]
    doc = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>railtraj QC report</title>"
           f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>")
    with atomic_write(path) as fh:
        fh.write(doc)


def _header(result, metrics: dict[str, Any]) -> str:
    c = metrics["counts"]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in metrics.get("notes", []))
    return (f"<h1>railtraj QC report</h1><p>Survey <code>{html.escape(str(result.survey.root))}</code>, "
            f"pipeline <b>{html.escape(result.options.mode)}</b>: {c['runs']} runs, {c['tiles']} tiles, "
            f"{c['tile_pairs']} tile pairs, {c['ties']} ties, {c['anchors']} anchors.</p>"
            + (f"<div class='note'><b>Warnings</b><ul>{notes}</ul></div>" if notes else ""))


def _summary(result, metrics, places, secs, clouds, chainage: Chainage) -> str:
    counts = {v: sum(p.verdict == v for p in places) for v in VERDICTS}
    qc = metrics["qc"]
    cards = [(f"{counts[v]}", f"tile pairs {v}", COLOURS[v]) for v in VERDICTS]
    cards += [(f"{mm(qc['c2c_before_m'].get('median')):.0f} → {mm(qc['c2c_after_m'].get('median')):.0f} mm",
               "C2C median between runs, before → after", "#444")]
    if "truth" in metrics:
        b, a = metrics["truth"]["before"]["overall"], metrics["truth"]["after"]["overall"]
        cards.append((f"{mm(b.get('rms_3d')):.0f} → {mm(a.get('rms_3d')):.0f} mm", "RMS error vs truth", "#444"))
    card_html = "".join(f"<div class='card' style='border-top:5px solid {col}'><b>{html.escape(v)}</b>"
                        f"{html.escape(t)}</div>" for v, t, col in cards)
    by_pair = {c.index: c for c in clouds}
    rows = []
    for s in secs:
        before = [by_pair[k].median_before for k in s.pairs if k in by_pair]
        after = [by_pair[k].median_after for k in s.pairs if k in by_pair]
        rows.append({"runs": s.runs, "from [m]": round(s.start), "to [m]": round(s.end), "tile pairs": len(s.pairs),
                     "verdict": Badge(s.verdict, COLOURS[s.verdict]),
                     "C2C median before [mm] (worst pair)": mm(np.nanmax(before)) if before else float("nan"),
                     "C2C median after [mm] (worst pair)": mm(np.nanmax(after)) if after else float("nan")})
    legend = ("<p><b>aligned</b>: fixed in all three directions; <b>weak along-track</b>: across and height "
              "fixed, along the track carried from neighbouring sections; <b>unresolved</b>: a rib or "
              "sleeper alias could not be ruled out, only across and height used; <b>refused</b>: no reliable "
              f"match. Chainage is the distance along {html.escape(chainage.run_id)}'s input trajectory.</p>")
    strip = _img(figures.verdict_strip(secs, places, chainage), "verdict per section") if secs else ""
    return (f"<h2>Summary</h2><div class='cards'>{card_html}</div><h3>Verdict per tunnel section</h3>{strip}"
            f"{legend}{table(rows)}")


def _corrections(result, chainage: Chainage) -> str:
    rows = []
    for run_id in sorted(result.trajectories):
        corr = result.corrected[run_id].xyz - result.trajectories[run_id].xyz
        sd = result.corrected[run_id].sd
        row = {"run": run_id, **{f"max |{a}| [mm]": mm(np.abs(corr[:, k]).max()) for k, a in enumerate("ENU")}}
        row.update({f"median sd {a} [mm]": mm(np.median(sd[:, k])) if sd is not None else float("nan")
                    for k, a in enumerate("ENU")})
        rows.append(row)
    return ("<h2>Correction applied to each run</h2><p>Corrected minus input position of the trajectory "
            "(east, north, up); the band is the posterior 1-sigma of the adjustment.</p>"
            f"{_img(figures.corrections(result, chainage), 'corrections per run')}{table(rows)}")


def _misalignment(result, metrics, places, clouds, chainage: Chainage) -> str:
    qc = metrics["qc"]
    stats = [{"figure": name, "n": qc[key].get("n"), **{f"{k} [mm]": mm(qc[key].get(k))
                                                        for k in ("median", "rms", "p95", "max")}}
             for name, key in (("tie residual before", "tie_residual_before_m"),
                               ("tie residual after", "tie_residual_after_m"),
                               ("C2C before", "c2c_before_m"), ("C2C after", "c2c_after_m"))]
    if not clouds:
        return f"<h2>Misalignment between runs</h2>{table(stats)}<p class='none'>no point samples</p>"
    picks = pick_pairs(clouds)
    sections_html = ""
    if picks:
        sections_html = ("<h3>Cross-sections: the worst and a typical tile pair</h3><p>A thin slice across "
                         "the track through both runs' points; after correction the two colours should "
                         "lie on one another.</p>"
                         + _img(figures.cross_sections(picks, places, chainage, result), "cross-sections"))
    return ("<h2>Misalignment between runs</h2><p>Cloud-to-cloud (C2C): distance from each sampled point of "
            "run b to the nearest point of run a in the overlap of a tile pair (capped at 1 m).</p>"
            f"{table(stats)}<h3>Plan view</h3>"
            f"{_img(figures.plan_map(result, places, clouds), 'plan view of C2C per tile')}"
            f"<h3>C2C distances, all tile pairs</h3>{_img(figures.c2c_histograms(clouds), 'C2C histograms')}"
            f"{sections_html}")


def _problem_pairs(result, metrics, places) -> str:
    along = {(r["tile_a"], r["tile_b"], r["run_a"], r["run_b"]): r
             for r in (metrics.get("adjustment") or {}).get("alongtrack") or []}
    rows = []
    for p in places:
        o = result.pairs[p.index].offset
        if o.status == "ok":
            continue
        rows.append({"runs": p.runs, "tile a": o.tile_a, "tile b": o.tile_b, "chainage [m]": round(p.chainage),
                     "status": Badge(o.status, COLOURS[p.verdict]),
                     "reason": pair_reason(o, along.get((o.tile_a, o.tile_b, o.run_a, o.run_b)))})
    return (f"<h2>Refused and ambiguous tile pairs ({len(rows)})</h2>"
            f"{table(sorted(rows, key=lambda r: (r['runs'], r['chainage [m]'])), 'left')}")


def _control(metrics) -> str:
    control = metrics.get("control") or []
    if not control:
        return ""
    rows = [{"point": c["id"], "run": c["run_id"], "source": c.get("source", ""),
             **{f"{a} before [mm]": mm(c["before_m"][k]) for k, a in enumerate("ENU")},
             **{f"{a} after [mm]": mm(c["after_m"][k]) for k, a in enumerate("ENU")},
             "horizontal before → after [mm]": f"{mm(c['horizontal_before']):.0f} → {mm(c['horizontal_after']):.0f}"}
            for c in control]
    return ("<h2>Control points</h2><p>Residual = surveyed minus seen in the run's cloud, before and after "
            f"correction.</p>{table(rows)}")


def _truth(result, metrics, truth_dir: Path | None, chainage: Chainage) -> str:
    truth = metrics.get("truth")
    if not truth:
        return ""
    plot = ""
    if truth_dir is not None:
        from railtraj.report.truth import errors_along_chainage
        try:
            plot = _img(figures.truth_errors(errors_along_chainage(result, truth_dir, chainage), chainage.run_id),
                        "error along chainage")
        except Exception as exc:  # a report must not fail on the optional truth plot
            log.warning("truth plot skipped: %s", exc)
    runs = [{"run": r, **{f"{k} {w} [mm]": mm(truth[w]["runs"][r].get(k)) for k in ("rms_h", "rms_v", "max_h")
                          for w in ("before", "after")}} for r in sorted(truth["before"]["runs"])]
    cons = [{"runs": pair, **{f"{k} {w} [mm]": mm(truth[w]["consistency"][pair].get(k))
                              for k in ("rms_h", "rms_v", "max_h") for w in ("before", "after")}}
            for pair in sorted(truth["before"].get("consistency", {}))]
    off = truth.get("tile_offsets") or {}
    off_rows = [{"ok pairs": off.get("ok_pairs", 0), **{f"RMS {a} [mm]": mm(v) for a, v in zip("ENU", off.get("rms_m") or [], strict=False)},
                 **{f"max |{a}| [mm]": mm(v) for a, v in zip("ENU", off.get("max_abs_m") or [], strict=False)},
                 "within 1 cm": off.get("within_1cm")}] if off else []
    return ("<h2>Against the simulator's truth</h2><p>Position error of each run's trajectory, input (dotted) "
            f"and corrected (solid).</p>{plot}<h3>Per run</h3>{table(runs)}<h3>Between runs (what misaligns "
            f"their clouds)</h3>{table(cons)}<h3>Tile-pair offsets marked ok</h3>{table(off_rows)}")


def _details(result, metrics, places, clouds) -> str:
    by_pair = {c.index: c for c in clouds}
    pairs = [{"runs": p.runs, "tile a": p.tile_a, "tile b": p.tile_b, "chainage [m]": round(p.chainage),
              "status": Badge(p.status, COLOURS[p.verdict]),
              **{f"d{a} [m]": float(result.pairs[p.index].offset.d[k]) for k, a in enumerate("xyz")},
              **{f"sd {a} [mm]": mm(np.sqrt(result.pairs[p.index].offset.cov[k, k])) for k, a in enumerate("xyz")},
              "inliers": result.pairs[p.index].offset.inliers,
              "C2C before [mm]": mm(by_pair[p.index].median_before) if p.index in by_pair else float("nan"),
              "C2C after [mm]": mm(by_pair[p.index].median_after) if p.index in by_pair else float("nan")}
             for p in places]
    seconds = {k: v for k, v in metrics.get("seconds", {}).items()}
    return (f"<h2>Details</h2><details><summary>All tile pairs ({len(pairs)})</summary>{table(pairs)}</details>"
            f"{_adjustment(metrics)}"
            f"<details><summary>Configuration</summary>{table(key_values(metrics.get('config') or {}), 'left')}</details>"
            f"<details><summary>Timings [s]</summary>{table(key_values(seconds), 'left')}</details>")


def _adjustment(metrics: dict[str, Any]) -> str:
    """What the optimizer used and rejected, where it was unconstrained, the along-track resolution."""
    adj = metrics.get("adjustment") or {}
    parts = []
    if adj.get("observations"):
        rows = [{"observations": k, **v} for k, v in adj["observations"].items()]
        parts.append(f"{table(rows)}<p>{adj.get('gnc_iterations', 0)} robust iterations (GNC, truncated least "
                     f"squares), {adj.get('knots', 0)} knots.</p>")
    if adj.get("alongtrack"):
        rows = [{k: v for k, v in r.items() if k != "candidate_shifts_m"} for r in adj["alongtrack"]]
        fixed = sum(r["status"] == "ok" for r in rows)
        parts.append(f"<h4>Along the track: {fixed} of {len(rows)} tile pairs with alias candidates fixed</h4>"
                     "<p>shift: the alias chosen, relative to the matcher's own offset (m); margin: how much "
                     f"better it fits the chain than the runner-up (chi-square; fixed from 16)</p>{table(rows)}")
    if adj.get("rejected"):
        parts.append(f"<h4>Rejected observations (first {len(adj['rejected'])})</h4>{table(adj['rejected'])}")
    if adj.get("under_constrained"):
        parts.append(f"<h4>Stretches with no observation</h4>{table(adj['under_constrained'])}")
    return f"<details><summary>Global adjustment</summary>{''.join(parts)}</details>" if parts else ""
