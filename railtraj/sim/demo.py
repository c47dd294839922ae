"""The built-in demo survey: the ``mixed`` scenario, generated once and cached.

``railtraj`` with no ``survey_dir`` runs on this. The cache folder's name carries a hash of the
code that produces the files, so a change to the simulator (or to the LAS/CSV writers) makes a
fresh demo instead of silently reusing a stale one. The demo is generated into a hidden temporary
folder and renamed into place, so a killed run never leaves a half survey that looks complete,
and two processes racing to build it both end up with one good copy.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
from pathlib import Path

from railtraj import __version__
from railtraj.cache import default_cache_dir
from railtraj.sim.scenarios import CATALOGUE, DEMO
from railtraj.sim.simulate import generate

log = logging.getLogger(__name__)
DEMO_SEED = 0
#: Modules whose code determines the demo's files.
_SOURCES = ("sim/track.py", "sim/sections.py", "sim/mesh.py", "sim/objects.py", "sim/geometry.py",
            "sim/surfaces.py", "sim/scanner.py", "sim/runs.py", "sim/drift.py", "sim/scenarios.py",
            "sim/writer.py", "sim/simulate.py", "georef.py", "io/las.py", "io/trajectory_csv.py")


def demo_key() -> str:
    """``<version>-<hash>`` of the demo's scenario, seed and generating code."""
    h = hashlib.sha256(repr((CATALOGUE[DEMO], DEMO_SEED)).encode())
    root = Path(__file__).resolve().parent.parent
    for name in _SOURCES:
        path = root / name
        h.update(name.encode() + (path.read_bytes() if path.is_file() else b""))
    return f"{__version__}-{h.hexdigest()[:12]}"


def demo_dir(cache_dir: str | os.PathLike | None = None) -> Path:
    """Folder holding the demo's ``survey`` and ``truth`` (it may not exist yet)."""
    base = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return base / f"demo-{demo_key()}"


def demo_survey(cache_dir: str | os.PathLike | None = None) -> Path:
    """Path of the demo survey folder, generating it first if it is not cached yet.

    Its truth is in the sibling folder ``truth`` (``demo_survey().parent / "truth"``).
    """
    final = demo_dir(cache_dir)
    if (final / "survey").is_dir():
        return final / "survey"
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    try:
        log.info("generating the demo survey (scenario %r) into %s", DEMO, final)
        generate(DEMO, tmp, seed=DEMO_SEED)
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "survey").is_dir():   # not a lost race: a real failure
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final / "survey"
