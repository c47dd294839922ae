"""HTML tables for the report: escaping, number formatting and the row builders of each table.

Numbers are shown in the unit a surveyor reads: millimetres for misalignments and residuals,
metres for chainage, seconds for timings.
"""

from __future__ import annotations

import html
from typing import Any

import numpy as np


def table(rows: list[dict[str, Any]], cls: str = "") -> str:
    """An HTML table of ``rows`` (dicts with the same keys); "none" when empty."""
    if not rows:
        return "<p class='none'>none</p>"
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in rows[0])
    digits = [_digits(str(k)) for k in rows[0]]
    body = "".join("<tr>" + "".join(_cell(v, n) for v, n in zip(r.values(), digits, strict=False))
                   + "</tr>" for r in rows)
    return f"<table class='{cls}'><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _digits(header: str) -> int:
    """Decimals by the column's unit: 0.1 mm, 1 mm in metres, 10 ms."""
    return 1 if "[mm]" in header else 2 if "[s]" in header else 3


def _cell(v: Any, digits: int = 3) -> str:
    if isinstance(v, Badge):
        style = f"background:{v.colour}"
        return f"<td><span class='badge' style='{style}'>{html.escape(v.text)}</span></td>"
    return f"<td>{html.escape(fmt(v, digits))}</td>"


class Badge:
    """A table cell drawn as a coloured label (a verdict)."""

    def __init__(self, text: str, colour: str) -> None:
        self.text, self.colour = text, colour


def fmt(v: Any, digits: int = 3) -> str:
    """Plain text of a cell: floats to ``digits`` decimals, NaN/None blank."""
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.{digits}f}"
    if isinstance(v, (list, tuple)):
        return ", ".join(fmt(x, digits) for x in v)
    return str(v)


def mm(v: Any) -> float:
    """Metres to millimetres (NaN for missing)."""
    try:
        return round(float(v) * 1000.0, 1)
    except (TypeError, ValueError):
        return float("nan")


def key_values(data: Any, prefix: str = "") -> list[dict[str, Any]]:
    """Nested dicts flattened to (key, value) rows: configuration and timings without JSON dumps."""
    if isinstance(data, dict):
        rows = []
        for k, v in data.items():
            rows += key_values(v, f"{prefix}.{k}" if prefix else str(k))
        return rows
    return [{"key": prefix, "value": fmt(data, 3) if isinstance(data, float) else fmt(data)}]
