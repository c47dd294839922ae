"""The ``identity`` optimizer: returns every trajectory unchanged.

An honest placeholder and a baseline for comparisons: with it, railtraj still matches tiles,
writes offsets, ties and QC figures, so a surveyor sees the misalignment before correction.
The posterior sd is the input sd (nothing was learned).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.hookspecs import hookimpl


@dataclass
class IdentityConfig:
    name: str = "identity"


class IdentityOptimizer:
    """Leaves the trajectories as they are."""

    def optimize(self, trajectories: dict[str, Trajectory], ties: Sequence[Ties],
                 offsets: Sequence[TileOffset]) -> dict[str, Trajectory]:
        return dict(trajectories)


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("optimizer", "identity", IdentityOptimizer, IdentityConfig)
