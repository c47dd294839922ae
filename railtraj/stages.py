"""The interfaces of the swappable stages: one ``typing.Protocol`` per stage kind.

A stage is built from its config by the plugin that registered it (``factory(**options)``) and
then only these methods are called. The registry checks a built stage against its protocol and
names the plugin when it does not fit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol, TypeVar, runtime_checkable

from railtraj.data import Keypoints, PointTile, Ties, TileOffset, Trajectory

T = TypeVar("T")
R = TypeVar("R")


@runtime_checkable
class Detector(Protocol):
    """Finds repeatable 3-D keypoints in one tile; each keeps the gps_time of the point it stands for."""

    def detect(self, tile: PointTile) -> Keypoints: ...


@runtime_checkable
class Descriptor(Protocol):
    """Attaches a descriptor vector to each keypoint (or leaves them without: ``none``)."""

    def describe(self, tile: PointTile, keypoints: Keypoints) -> Keypoints: ...


@runtime_checkable
class Matcher(Protocol):
    """Estimates the translation that moves tile ``b`` onto tile ``a`` and the matched features.

    ``initial`` is an earlier estimate (from a previous matcher in a chain) or None.
    Must return a :class:`TileOffset` whose ``status`` is not ``"ok"`` when there is no reliable
    match, rather than a confident wrong translation.
    """

    def match(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints,
              initial: TileOffset | None = None) -> TileOffset: ...


@runtime_checkable
class Optimizer(Protocol):
    """Corrects the runs' trajectories so that the matched features agree.

    Returns one trajectory per run with the same epochs; ``sd`` holds the posterior 1-sigma.
    An optimizer that uses control points takes a keyword argument ``control``
    (:class:`ControlObservations`); the pipeline passes it only then, and otherwise warns that the
    survey's control was not used. After ``optimize`` an optional ``diagnostics`` dict (counts,
    rejected observations, ``notes``) is written to metrics.json and the report.
    """

    def optimize(self, trajectories: dict[str, Trajectory], ties: Sequence[Ties],
                 offsets: Sequence[TileOffset]) -> dict[str, Trajectory]: ...


@runtime_checkable
class Executor(Protocol):
    """Maps a function over work items (tiles, tile pairs), serially or in parallel.

    ``fn`` and the items must be picklable for executors that use processes. Results come back in
    the order of ``items``. ``progress(done, total)`` is called as items finish. An executor that
    holds resources (the ``dask`` cluster) may have a ``close()``; the CLI calls it when the job
    ends, also on error.
    """

    def map(self, fn: Callable[[T], R], items: Iterable[T],
            progress: Callable[[int, int], Any] | None = None) -> list[R]: ...


#: stage kind -> protocol; the registry validates against this table.
STAGE_KINDS: dict[str, type] = {
    "detector": Detector,
    "descriptor": Descriptor,
    "matcher": Matcher,
    "optimizer": Optimizer,
    "executor": Executor,
}
