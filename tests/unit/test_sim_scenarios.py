"""The scenario catalogue: names, freezing, scaling, and no config framework under sim/."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

import railtraj.sim
from railtraj.errors import ConfigError
from railtraj.sim.scenarios import CATALOGUE, DEMO, MIN_POINTS, MIN_SECTION, get_scenario


def test_catalogue_has_the_promised_scenarios():
    assert {"thesis", "mixed", "portal_trap", "control", "feature_poor"} <= set(CATALOGUE)
    assert DEMO == "mixed"
    demo = CATALOGUE["mixed"]
    tunnel = sum(n for k, n in demo.geometry.sections if k != "cutting")
    assert 550 <= tunnel <= 650 and len(demo.runs) == 3
    assert {r.track for r in demo.runs} == {0, 1} and {r.direction for r in demo.runs} == {1, -1}
    assert {"rect", "station", "circular", "cutting"} <= {k for k, _ in demo.geometry.sections}
    assert CATALOGUE["control"].geometry.control_spacing
    assert CATALOGUE["portal_trap"].drift.multipath
    assert {k for k, _ in CATALOGUE["feature_poor"].geometry.sections} == {"cutting", "circular"}
    for scn in CATALOGUE.values():
        assert len({r.run_id for r in scn.runs}) == len(scn.runs) >= 2
        json.dumps(scn.to_dict())


def test_scenarios_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        CATALOGUE["thesis"].name = "x"


def test_scaling():
    full = get_scenario("mixed")
    small = get_scenario("mixed", size=0.1)
    assert small.size == pytest.approx(0.1) and full.size == 1.0
    assert all(n >= MIN_SECTION for _, n in small.geometry.sections)
    assert small.geometry.length < 0.25 * full.geometry.length
    assert small.scanner.points_per_profile == max(MIN_POINTS, round(0.1 ** 0.5 * full.scanner.points_per_profile))
    assert small.geometry.rib_spacing == full.geometry.rib_spacing
    assert get_scenario("mixed", 1.0) is CATALOGUE["mixed"]


def test_bad_names_and_sizes_say_what_to_do():
    with pytest.raises(ConfigError, match="choose from .*thesis"):
        get_scenario("nope")
    with pytest.raises(ConfigError, match="positive"):
        get_scenario("thesis", size=0)


def test_no_config_framework_under_sim():
    folder = Path(railtraj.sim.__file__).parent
    for path in folder.glob("*.py"):
        text = path.read_text()
        assert "import hydra" not in text and "omegaconf" not in text, path.name


def test_lazy_front_door():
    assert railtraj.sim.get_scenario is get_scenario
    with pytest.raises(AttributeError):
        railtraj.sim.nothing_here  # noqa: B018
