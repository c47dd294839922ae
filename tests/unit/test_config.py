"""Hydra composition: every option of every stage group composes and builds."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize, initialize_config_dir
from omegaconf import OmegaConf

import railtraj.cli as cli
from railtraj.errors import PluginError
from railtraj.plugins import registry
from railtraj.stages import STAGE_KINDS

CONF = Path(__file__).resolve().parents[2] / "conf"


def _compose(overrides):
    with initialize(version_base="1.3", config_path=None):
        return compose(config_name="railtraj", overrides=overrides)


def test_default_config_builds_every_stage():
    cfg = _compose([])
    stages = cli.build_stages(cfg)
    for kind, proto in STAGE_KINDS.items():
        assert isinstance(getattr(stages, kind), proto)
    assert cfg.pipeline.name == "global" and cfg.survey_dir is None


@pytest.mark.parametrize("kind,name", [(s.kind, s.name) for s in registry().specs()])
def test_every_option_composes_and_instantiates(kind, name):
    cfg = _compose([f"{kind}={name}"])
    assert cfg[kind].name == name
    stage = registry().create(kind, name, OmegaConf.to_container(cfg[kind]))
    assert isinstance(stage, STAGE_KINDS[kind])


@pytest.mark.parametrize("pipeline", ["local", "global", "multirun"])
def test_pipelines_compose(pipeline):
    cfg = _compose([f"pipeline={pipeline}"])
    assert cfg.pipeline.name == pipeline
    assert cfg.pipeline.pairs in ("reference", "all")


def test_typed_options_are_checked():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException):
        _compose(["detector=voxel_corner", "detector.voxel_size=abc"])
    with pytest.raises(ConfigCompositionException):
        _compose(["detector=voxel_corner", "detector.bogus=1"])
    # appending an unknown key gets past Hydra (the group node is typed Any) but not the registry
    with pytest.raises(PluginError, match="has no option bogus"):
        cli.build_stages(_compose(["detector=voxel_corner", "+detector.bogus=1"]))
    with pytest.raises(ConfigCompositionException):
        _compose(["detector=no_such_detector"])


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_experiment_presets_compose(preset):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose(config_name="railtraj", overrides=[f"+experiment={preset}"])
    cli.build_stages(cfg)
