"""A small PNG of one tile pair's translation votes, for the QC report.

Three histograms through the winning translation (along x, y and z, each of the votes that
agree with it in the other two axes) show how sharp the peak is and where the aliases are (in a
tunnel: side peaks along the track at the rib and sleeper spacing). A fourth panel is the dense
fitness while sliding tile b along the weak axis (every alias is a bump), and a fifth lists the
offsets that were checked on the dense clouds: votes against fitness, the chosen one marked
(rows with 0 votes came from that profile, not from the vote).
Uses matplotlib's Agg canvas directly (no pyplot, no display, safe in worker processes).
"""

from __future__ import annotations

import os

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from railtraj.data import TileOffset


def plot_votes(offset: TileOffset, path: str | os.PathLike, dpi: int = 90) -> None:
    """Write the vote figure of ``offset`` (from ``offset.info``) to the PNG ``path``."""
    info = offset.info or {}
    fig = Figure(figsize=(12.5, 2.6))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 5)
    slices = info.get("vote_slices")
    title = f"{offset.tile_a} / {offset.tile_b}: {offset.status}"
    if np.isfinite(offset.d).all():
        title += "  d = (" + ", ".join(f"{v:+.3f}" for v in offset.d) + ") m"
    fig.suptitle(title, fontsize=9)
    for k, axis in enumerate("xyz"):
        ax = axes[k]
        if slices and axis in slices:
            counts = np.asarray(slices[axis], float)
            edges = slices["start"] + slices["bin"] * np.arange(len(counts) + 1)
            ax.stairs(counts, edges, fill=True, color="tab:blue")
        else:
            ax.text(0.5, 0.5, "no votes", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(f"d{axis} - peak (m)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("votes", fontsize=8)
    _profile_panel(axes[3], info)
    _peak_panel(axes[4], info)
    fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=dpi)


def _profile_panel(ax, info: dict) -> None:
    """Dense fitness against the shift along the weak axis from the leading hypothesis."""
    prof = info.get("alias_profile")
    ax.set_xlabel("shift along weak axis (m)", fontsize=8)
    ax.set_ylabel("fitness", fontsize=8)
    ax.tick_params(labelsize=7)
    if not prof or not prof.get("fitness"):
        ax.text(0.5, 0.5, "no profile", ha="center", va="center", transform=ax.transAxes)
        return
    fit = np.asarray(prof["fitness"], float)
    ax.plot(prof["start"] + prof["step"] * np.arange(len(fit)), fit, lw=1, color="tab:blue")
    ax.axvline(0.0, color="tab:red", lw=0.8)


def _peak_panel(ax, info: dict) -> None:
    """Votes against dense-check fitness of the checked peaks; the chosen one in red."""
    peaks = np.asarray(info.get("vote_peaks") or np.zeros((0, 5)), float).reshape(-1, 5)
    ax.set_xlabel("fitness (share within 5 cm)", fontsize=8)
    ax.set_ylabel("votes", fontsize=8)
    ax.tick_params(labelsize=7)
    if len(peaks) == 0 or not np.isfinite(peaks[:, 4]).any():
        ax.text(0.5, 0.5, "no peaks checked", ha="center", va="center", transform=ax.transAxes)
        return
    chosen = int(info.get("chosen_peak", 0))
    colours = ["tab:red" if i == chosen else "tab:gray" for i in range(len(peaks))]
    ax.scatter(peaks[:, 4], peaks[:, 3], c=colours, s=18)
    for p in peaks:
        ax.annotate(f"{p[0]:+.2f}", (p[4], p[3]), fontsize=6, xytext=(3, 2), textcoords="offset points")
    ratio = info.get("rival_misfit_ratio")
    if ratio is not None:
        ax.set_title(f"rival misfit ratio {ratio:.2f}", fontsize=8)
