"""The plugin registry: built-ins and entry points, validation, and failures named by plugin."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.errors import PluginError
from railtraj.plugins import StageRegistry, registry
from railtraj.stages import STAGE_KINDS


def _fake_dist(root: Path, module_source: str, entry: str = "broken = broken_plugin") -> Path:
    """A minimal installed distribution (dist-info + module) with a `railtraj` entry point."""
    (root / "broken_plugin.py").write_text(textwrap.dedent(module_source))
    info = root / "broken_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[railtraj]\n{entry}\n")
    return root


def _run_plugins_cmd(extra_path: Path, **env) -> subprocess.CompletedProcess:
    environ = dict(os.environ, PYTHONPATH=str(extra_path), **env)
    code = "from railtraj.cli import list_plugins; list_plugins()"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environ, timeout=120)


def test_every_kind_has_builtins_and_example_plugin_is_found():
    reg = registry()
    for kind in STAGE_KINDS:
        assert reg.names(kind), f"no built-in {kind}"
    spec = reg.get("detector", "voxel_corner")
    assert spec.plugin == "voxel_corner"          # registered from the entry point, not the source tree
    assert spec.options()["voxel_size"] > 0


def test_every_registered_stage_instantiates_with_defaults():
    reg = registry()
    for spec in reg.specs():
        stage = reg.create(spec.kind, spec.name, {})
        assert isinstance(stage, STAGE_KINDS[spec.kind]), spec


def test_example_plugin_detects_box_corners():
    rng = np.random.default_rng(1)
    wall = np.column_stack([rng.uniform(0, 10, 20000), np.zeros(20000), rng.uniform(0, 3, 20000)])
    box = rng.uniform(0, 0.4, (3000, 3)) + [5.0, 0.0, 1.0]   # a solid 40 cm box on the wall
    xyz = np.vstack([wall, box])
    tile = PointTile(xyz, np.linspace(100, 101, len(xyz)), run_id="a", name="t")
    kp = registry().create("detector", "voxel_corner", {"max_keypoints": 5}).detect(tile)
    assert len(kp) >= 1
    assert np.linalg.norm(kp.xyz[0] - [5.2, 0.2, 1.2]) < 0.4        # best keypoint is on the box
    assert 100 <= kp.gps_time.min() and kp.gps_time.max() <= 101


def test_unknown_stage_lists_choices():
    with pytest.raises(PluginError, match="available: .*identity"):
        registry().get("optimizer", "nope")


def test_unknown_option_lists_valid_ones():
    with pytest.raises(PluginError, match="has no option bogus.*voxel_size"):
        registry().create("detector", "voxel_corner", {"bogus": 1})


def test_registry_rejects_stage_that_does_not_fit_protocol():
    @dataclass
    class Cfg:
        name: str = "bad"

    class NotADetector:
        pass

    reg = StageRegistry()
    reg._current_plugin = "my_plugin"
    reg.add("detector", "bad", NotADetector, Cfg)
    with pytest.raises(PluginError, match="'my_plugin'.*does not implement Detector.*detect"):
        reg.create("detector", "bad", {})
    with pytest.raises(PluginError, match="unknown stage kind 'detecter'"):
        reg.add("detecter", "x", NotADetector, Cfg)
    with pytest.raises(PluginError, match="both register detector 'bad'"):
        reg.add("detector", "bad", NotADetector, Cfg)


def test_broken_entry_point_fails_with_plugin_name(tmp_path):
    _fake_dist(tmp_path, "import not_a_module_anywhere\n")
    res = _run_plugins_cmd(tmp_path)
    assert res.returncode == 2
    assert "plugin 'broken'" in res.stderr and "not_a_module_anywhere" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_autoload_can_be_switched_off(tmp_path):
    _fake_dist(tmp_path, "import not_a_module_anywhere\n")
    res = _run_plugins_cmd(tmp_path, RAILTRAJ_DISABLE_PLUGIN_AUTOLOAD="1")
    assert res.returncode == 0, res.stderr
    assert "voxel_corner" not in res.stdout and "identity" in res.stdout


def test_plugin_failing_during_registration_is_named(tmp_path):
    _fake_dist(tmp_path, """
        from railtraj.hookspecs import hookimpl
        @hookimpl
        def railtraj_register_stages(registry):
            raise RuntimeError("boom")
    """)
    res = _run_plugins_cmd(tmp_path)
    assert res.returncode == 2
    assert "plugin 'broken' failed while registering stages: RuntimeError: boom" in res.stderr
