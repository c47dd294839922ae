"""Every option of every local stage (detectors, descriptors, matchers) builds through the registry."""

from __future__ import annotations

import pytest

from railtraj.errors import ConfigError, PluginError
from railtraj.plugins import registry
from railtraj.stages import STAGE_KINDS

LOCAL_STAGES = [("detector", "iss"), ("detector", "harris3d"), ("descriptor", "fpfh"),
                ("descriptor", "none"), ("matcher", "mutual_nn"), ("matcher", "pair_voting"),
                ("matcher", "icp")]


@pytest.mark.parametrize("kind,name", LOCAL_STAGES)
def test_stage_builds_with_defaults_and_fits_its_protocol(kind, name):
    stage = registry().create(kind, name, {})
    assert isinstance(stage, STAGE_KINDS[kind])


@pytest.mark.parametrize("kind,name", LOCAL_STAGES)
def test_every_option_can_be_set_to_its_default(kind, name):
    reg = registry()
    options = reg.get(kind, name).options()
    for key, value in options.items():  # one at a time, as a command-line override would
        assert isinstance(reg.create(kind, name, {key: value}), STAGE_KINDS[kind])
    assert isinstance(reg.create(kind, name, dict(options, name=name)), STAGE_KINDS[kind])


@pytest.mark.parametrize("kind,name,options", [
    ("matcher", "icp", {"method": "kiss"}),
    ("matcher", "icp", {"translation_only": False}),
    ("matcher", "icp", {"tie_positions": "keypoints"}),
    ("matcher", "pair_voting", {"refine": False, "tie_positions": "keypoints"}),
    ("matcher", "mutual_nn", {"refine": False}),
    ("detector", "harris3d", {"response": "tomasi"}),
    ("detector", "iss", {"voxel_size": 0.0, "max_keypoints": 700}),
])
def test_alternative_choices_build(kind, name, options):
    assert isinstance(registry().create(kind, name, options), STAGE_KINDS[kind])


@pytest.mark.parametrize("kind,name,options,words", [
    ("matcher", "icp", {"method": "gicp"}, "plane or kiss"),
    ("matcher", "pair_voting", {"tie_positions": "middle"}, "offset or keypoints"),
    ("matcher", "pair_voting", {"max_misalignment": 0.0}, "max_misalignment > 0"),
    ("detector", "harris3d", {"response": "noble"}, "harris or tomasi"),
    ("detector", "harris3d", {"voxel_size": 0.0}, "voxel_size > 0"),
    ("detector", "iss", {"salient_radius": 0.0}, "salient_radius > 0"),
    ("descriptor", "fpfh", {"feature_radius": -1.0}, "feature_radius > 0"),
])
def test_bad_choices_say_what_is_valid(kind, name, options, words):
    with pytest.raises((ConfigError, PluginError), match=words):
        registry().create(kind, name, options)


def test_unknown_option_lists_the_valid_ones():
    with pytest.raises(PluginError, match="inlier_radius"):
        registry().create("matcher", "pair_voting", {"inlier_radious": 0.1})
