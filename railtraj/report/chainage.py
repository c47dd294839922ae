"""Chainage for the report: :class:`railtraj.chainage.Chainage` along the reference run."""

from __future__ import annotations

from railtraj.chainage import Chainage


def reference_run(runs: list[str], configured: str | None) -> str:
    """The run the report measures chainage along: the pipeline's reference run, else the first."""
    return configured if configured in runs else sorted(runs)[0]


__all__ = ["Chainage", "reference_run"]
