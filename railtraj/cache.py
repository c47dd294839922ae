"""railtraj's per-user cache folder: things built once on a machine and reused (the demo survey,
the OSTN15 grid). Deleting it is always safe; whatever is needed is built again."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """``$RAILTRAJ_CACHE`` or ``$XDG_CACHE_HOME/railtraj`` or ``~/.cache/railtraj``."""
    if os.environ.get("RAILTRAJ_CACHE"):
        return Path(os.environ["RAILTRAJ_CACHE"])
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "railtraj"
