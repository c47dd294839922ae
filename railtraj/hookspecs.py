"""Every hook a railtraj plugin can implement. This module is the plugin reference.

A plugin is a module (or object) with functions marked ``@hookimpl``; railtraj finds built-in
plugins in :data:`railtraj.builtins.BUILTIN_PLUGINS` and third-party ones through the
``railtraj`` entry-point group (see docs/plugins.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:
    from railtraj.plugins import StageRegistry

hookspec = pluggy.HookspecMarker("railtraj")
hookimpl = pluggy.HookimplMarker("railtraj")


@hookspec
def railtraj_register_stages(registry: StageRegistry) -> None:
    """Register stage implementations.

    Call ``registry.add(kind, name, factory, config)`` once per stage, where ``kind`` is one of
    detector, descriptor, matcher, optimizer, executor; ``name`` is what users type
    (``detector=<name>``); ``factory`` is called with the config's fields as keyword arguments
    and must return an object satisfying the kind's protocol in :mod:`railtraj.stages`;
    ``config`` is a dataclass whose fields (with defaults) are the stage's options. The registry
    publishes the config to Hydra, so options are checked and overridable from the command line.
    """


@hookspec
def railtraj_metrics(result: Any) -> dict[str, Any] | None:
    """Add figures to OUT/metrics.json after a pipeline has run.

    ``result`` is the pipeline's :class:`railtraj.pipeline.PipelineResult`. Return a dict of
    JSON-serialisable values (merged under the key ``"plugins"``) or None.
    """
