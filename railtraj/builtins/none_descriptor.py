"""The ``none`` descriptor: keypoints go to the matcher as they are.

What the thesis ended up using: FPFH did not separate tunnel features (no correlation between
descriptor distance and correct matches) and cost more than the rest of the pipeline, so the
keypoints went straight to the exhaustive-pair outlier removal (``matcher=pair_voting``).
"""

from __future__ import annotations

from dataclasses import dataclass

from railtraj.data import Keypoints, PointTile
from railtraj.hookspecs import hookimpl


@dataclass
class NoneDescriptorConfig:
    name: str = "none"


class NoneDescriptor:
    """Returns the keypoints unchanged."""

    def describe(self, tile: PointTile, keypoints: Keypoints) -> Keypoints:
        return keypoints


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("descriptor", "none", NoneDescriptor, NoneDescriptorConfig)
