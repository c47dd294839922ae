"""OUT/report.html: the QC report a surveyor reads, one self-contained file (plots inlined).

Order of the page, most important first: a summary with a verdict per tunnel section, the
correction applied to each run, inter-run misalignment before and after (plan view, C2C
histograms, cross-sections), the pairs that were refused or left ambiguous and why, control
residuals, errors against the truth (simulated surveys only), then the details (all tile
pairs, the adjustment, configuration and timings) collapsed.
Plots come from :mod:`~railtraj.report.figures`, verdicts from :mod:`~railtraj.report.sections`,
table rows from :mod:`~railtraj.report.rows`; this module only assembles the page.
"""

from __future__ import annotations

import base64
import html
import logging
from pathlib import Path
from typing import Any

from railtraj.errors import RailtrajError
from railtraj.io.atomic import atomic_write
from railtraj.qc import PairClouds, pair_clouds
from railtraj.report import figures, rows
from railtraj.report.chainage import Chainage, reference_run
from railtraj.report.clouds import pick_pairs
from railtraj.report.sections import COLOURS, VERDICTS, place_pairs, sections
from railtraj.report.tables import key_values, mm, table

log = logging.getLogger(__name__)

STYLE = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:72em;padding:0 1em}
table{border-collapse:collapse;font-size:85%;margin:.5em 0}th{background:#eee}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}table.left td{text-align:left}
img{max-width:100%}h2{border-bottom:2px solid #ddd;margin-top:1.6em}
.badge{color:#fff;padding:1px 6px;border-radius:3px;white-space:nowrap}
.cards{display:flex;gap:1em;flex-wrap:wrap}.card b{font-size:160%;display:block}
.card{border:1px solid #ccc;border-radius:6px;padding:.5em 1em;min-width:9em}
details{margin:.6em 0}summary{cursor:pointer;font-weight:bold}p.none{color:#888}
.note{background:#fff4d6;padding:.3em .6em;border-left:4px solid #ffbf00}"""

LEGEND = ("<p><b>aligned</b>: fixed in all three directions; <b>weak along-track</b>: across and "
          "height fixed, along the track carried from neighbouring sections; <b>unresolved</b>: a "
          "rib or sleeper alias could not be ruled out, only across and height used; "
          "<b>refused</b>: no reliable match. Chainage is the distance along {ref}'s input "
          "trajectory.</p>")


def write_report(path, result, metrics: dict[str, Any], truth_dir: Path | None = None,
                 clouds: list[PairClouds] | None = None) -> None:
    """Write the HTML report for a pipeline result and its metrics (and the truth, if simulated);
    ``clouds``: :func:`railtraj.qc.pair_clouds` of ``result``, computed here if not given."""
    ref = reference_run(sorted(result.trajectories), result.options.reference_run)
    page = Page(result, metrics, Chainage(result.trajectories[ref]),
                pair_clouds(result) if clouds is None else clouds)
    parts = [page.header(), page.summary(), page.corrections(), page.misalignment(),
             page.problem_pairs(), page.control(), page.truth(truth_dir), page.details()]
    doc = ("<!doctype html><html lang='en'><head><meta charset='utf-8'>"
           f"<title>railtraj QC report</title><style>{STYLE}</style></head>"
           f"<body>{''.join(parts)}</body></html>")
    with atomic_write(path) as fh:
        fh.write(doc)


def img(png: bytes, alt: str) -> str:
    """An <img> with the PNG inlined, so the report is one file."""
    data = base64.b64encode(png).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


class Page:
    """The report's parts, each an HTML fragment, sharing the result's derived data."""

    def __init__(self, result, metrics: dict[str, Any], chainage: Chainage, clouds: list[PairClouds]) -> None:
        self.result, self.metrics, self.chainage = result, metrics, chainage
        self.places = place_pairs(result, chainage)
        self.sections = sections(self.places)
        self.clouds = clouds
        self.by_pair = {c.index: c for c in self.clouds}

    def header(self) -> str:
        c, r = self.metrics["counts"], self.result
        notes = "".join(f"<li>{html.escape(n)}</li>" for n in self.metrics.get("notes", []))
        warn = f"<div class='note'><b>Warnings</b><ul>{notes}</ul></div>" if notes else ""
        return (f"<h1>railtraj QC report</h1><p>Survey <code>{html.escape(str(r.survey.root))}"
                f"</code>, pipeline <b>{html.escape(r.options.mode)}</b>: {c['runs']} runs, "
                f"{c['tiles']} tiles, {c['tile_pairs']} tile pairs, {c['ties']} ties, "
                f"{c['anchors']} anchors"
                f"{self._anchors_frame()}.</p>{warn}")

    def _anchors_frame(self) -> str:
        frame = self.metrics.get("anchors_crs")
        if not frame or not self.metrics["counts"]["anchors"]:
            return ""
        return f" (lat, lon, h_ell in <code>{html.escape(str(frame)[:40])}</code>)"

    def summary(self) -> str:
        qc = self.metrics["qc"]
        cards = [(str(sum(p.verdict == v for p in self.places)), f"tile pairs {v}", COLOURS[v])
                 for v in VERDICTS]
        c2c = (mm(qc["c2c_before_m"].get("median")), mm(qc["c2c_after_m"].get("median")))
        cards.append((f"{c2c[0]:.0f} → {c2c[1]:.0f} mm",
                      "C2C median between runs, before → after", "#444"))
        if "truth" in self.metrics:
            t = self.metrics["truth"]
            rms = [mm(t[w]["overall"].get("rms_3d")) for w in ("before", "after")]
            cards.append((f"{rms[0]:.0f} → {rms[1]:.0f} mm", "RMS error vs truth", "#444"))
        cards_html = "".join(f"<div class='card' style='border-top:5px solid {col}'>"
                             f"<b>{html.escape(v)}</b>{html.escape(t)}</div>"
                             for v, t, col in cards)
        strip = ""
        if self.sections:
            strip = img(figures.verdict_strip(self.sections, self.places, self.chainage),
                        "verdict per section")
        return (f"<h2>Summary</h2><div class='cards'>{cards_html}</div>"
                f"<h3>Verdict per tunnel section</h3>{strip}"
                f"{LEGEND.format(ref=html.escape(self.chainage.run_id))}"
                f"{table(rows.section_rows(self.sections, self.by_pair))}")

    def corrections(self) -> str:
        plot = img(figures.corrections(self.result, self.chainage), "corrections per run")
        return ("<h2>Correction applied to each run</h2><p>Corrected minus input position of the "
                "trajectory (east, north, up); the band is the posterior 1-sigma of the adjustment."
                f"</p>{plot}{table(rows.correction_rows(self.result))}")

    def misalignment(self) -> str:
        head = ("<h2>Misalignment between runs</h2><p>Cloud-to-cloud (C2C): distance from each "
                "sampled point of run b to the nearest point of run a in the overlap of a tile "
                f"pair (capped at 1 m).</p>{table(rows.qc_rows(self.metrics['qc']))}")
        if not self.clouds:
            return head + "<p class='none'>no point samples</p>"
        plan = img(figures.plan_map(self.result, self.places, self.clouds), "plan view of C2C")
        hist = img(figures.c2c_histograms(self.clouds), "C2C histograms")
        along = img(figures.offsets_along(self.result, self.places, self.chainage), "offsets")
        out = (f"{head}<h3>Plan view</h3>{plan}<h3>C2C distances, all tile pairs</h3>{hist}"
               "<h3>Tile-pair offsets along the track</h3><p>What the matcher measured per tile "
               "pair (run b's points move by d onto run a's); hollow: weak or unresolved; "
               f"refused pairs are left out.</p>{along}")
        picks = pick_pairs(self.clouds)
        if picks:
            xs = figures.cross_sections(picks, self.places, self.chainage, self.result)
            out += ("<h3>Cross-sections: the worst and a typical tile pair</h3><p>A thin slice "
                    "across the track through both runs' points; after correction the two colours "
                    f"should lie on one another.</p>{img(xs, 'cross-sections')}")
        return out

    def problem_pairs(self) -> str:
        alongtrack = (self.metrics.get("adjustment") or {}).get("alongtrack") or []
        found = rows.problem_rows(self.result, self.places, alongtrack)
        return f"<h2>Refused and ambiguous tile pairs ({len(found)})</h2>{table(found, 'left')}"

    def control(self) -> str:
        control = self.metrics.get("control") or []
        if not control:
            return ""
        return ("<h2>Control points</h2><p>Residual = surveyed minus seen in the run's cloud, "
                f"before and after correction.</p>{table(rows.control_rows(control))}")

    def truth(self, truth_dir: Path | None) -> str:
        truth = self.metrics.get("truth")
        if not truth:
            return ""
        plot = ""
        if truth_dir is not None:
            from railtraj.report.truth import errors_along_chainage
            try:
                errors = errors_along_chainage(self.result, truth_dir, self.chainage)
                png = figures.truth_errors(errors, self.chainage.run_id)
                plot = img(png, "error along chainage")
            except (RailtrajError, OSError, ValueError, KeyError) as exc:  # optional plot
                log.warning("truth plot skipped: %s", exc)
        return ("<h2>Against the simulator's truth</h2><p>Position error of each run's trajectory, "
                f"input (dotted) and corrected (solid).</p>{plot}"
                f"<h3>Per run</h3>{table(rows.truth_rows(truth, 'runs'))}"
                "<h3>Between runs (what misaligns their clouds)</h3>"
                f"{table(rows.truth_rows(truth, 'consistency'))}"
                f"<h3>Tile-pair offsets marked ok</h3>{table(rows.offset_truth_rows(truth))}")

    def details(self) -> str:
        pairs = rows.pair_rows(self.result, self.places, self.by_pair)
        config = table(key_values(self.metrics.get("config") or {}), "left")
        seconds = table(key_values(self.metrics.get("seconds") or {}), "left")
        return (f"<h2>Details</h2><details><summary>All tile pairs ({len(pairs)})</summary>"
                f"{table(pairs)}</details>{adjustment(self.metrics)}"
                f"<details><summary>Configuration</summary>{config}</details>"
                f"<details><summary>Timings [s]</summary>{seconds}</details>")


def adjustment(metrics: dict[str, Any]) -> str:
    """What the optimizer used and rejected, where it was unconstrained, along-track resolution."""
    adj = metrics.get("adjustment") or {}
    parts = []
    if adj.get("observations"):
        obs = [{"observations": k, **v} for k, v in adj["observations"].items()]
        parts.append(f"{table(obs)}<p>{adj.get('gnc_iterations', 0)} robust iterations (GNC, "
                     f"truncated least squares), {adj.get('knots', 0)} knots.</p>")
    if adj.get("alongtrack_coverage"):
        rows = [{"run pair": pair, "resolved (m)": f"{c['resolved_m']:.0f} of {c['length_m']:.0f}",
                 "share": f"{c['share']:.0%}",
                 "not resolved: run b's time (s), length (m), chain's sd (m)": "; ".join(
                     f"{u['time_b'][0]:.1f}-{u['time_b'][1]:.1f}, {u['length_m']:.0f}"
                     + ("" if u["worst_sd_m"] is None else f", {u['worst_sd_m']:.3f}") for u in c["unresolved"]) or "-"}
                for pair, c in adj["alongtrack_coverage"].items()]
        parts.append("<h4>Where the runs' along-track offset is resolved</h4><p>fixed by a tile pair, or "
                     "predicted (or reported) within pipeline.alongtrack.resolved_sd; elsewhere the runs are "
                     f"placed across the track and in height only</p>{table(rows)}")
    if adj.get("alongtrack"):
        along = [{k: v for k, v in r.items() if k != "candidate_shifts_m"}
                 for r in adj["alongtrack"]]
        fixed = sum(r["status"] == "ok" for r in along)
        parts.append(f"<h4>Along the track: {fixed} of {len(along)} tile pairs with alias "
                     "candidates fixed</h4><p>shift: the alias chosen, relative to the matcher's "
                     "own offset (m); margin: how much better it fits the chain than the runner-up "
                     f"(chi-square; fixed from 16)</p>{table(along)}")
    checked = (adj.get("sd_check") or {}).get("runs") or {}
    if checked:
        rows = [{"run": r, "spans (s)": ", ".join(f"{a:.1f}-{b:.1f}" for a, b in v["spans_s"]),
                 "against": ", ".join(v["against"]), "disagreement (m)": round(v["worst_disagreement_m"], 3),
                 "reported sd (m)": round(v["reported_sd_m"], 3),
                 "widened sd along/across/up (m)": " / ".join(f"{x:.3f}" for x in v["widened_sd_m"].values())}
                for r, v in checked.items()]
        parts.append("<h4>Reported sd contradicted by the other runs: widened before the adjustment</h4>"
                     f"{table(rows)}")
    if adj.get("rejected"):
        parts.append(f"<h4>Rejected observations (first {len(adj['rejected'])})</h4>"
                     f"{table(adj['rejected'])}")
    if adj.get("under_constrained"):
        parts.append(f"<h4>Stretches with no observation</h4>{table(adj['under_constrained'])}")
    if not parts:
        return ""
    return f"<details><summary>Global adjustment</summary>{''.join(parts)}</details>"
