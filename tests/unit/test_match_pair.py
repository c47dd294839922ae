"""A tile pair as the pipeline matches it (railtraj.pipeline.match_pair): both runs' tiles cut
on the same 25 m grid, each where its own drift puts it."""

from __future__ import annotations

import types
from dataclasses import replace

import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.io.las import read_header, read_tile, write_tile
from railtraj.io.survey import find_overlaps, with_context
from railtraj.matching.objects import CONTEXT_M
from railtraj.matching.synthetic import second_acquisition
from railtraj.pipeline import PipelineOptions, detect_tile, joined_tiles_note, match_pair
from railtraj.plugins import registry
from railtraj.sim import generate
from railtraj.sim.scenarios import get_scenario
from railtraj.sim.track import Alignment

SHIFT = np.array([-0.3, -2.1, 0.0])  # run b against run a: 2.1 m across (south), 0.3 m back


def _grid_tiles(tile: PointTile, folder) -> list:
    """``tile`` cut in the squares of the 25 m grid, written to ``folder``: their headers."""
    folder.mkdir()
    cell = np.floor(tile.xyz[:, :2] / 25.0).astype(int)
    headers = []
    for key in np.unique(cell, axis=0):
        path = folder / f"{key[0] * 25}_{key[1] * 25}.laz"
        write_tile(path, tile.subset((cell == key).all(axis=1)))
        headers.append(read_header(path))
    return headers


@pytest.fixture(scope="module")
def cut_lengthwise(tmp_path_factory):
    """The commensurate scenario's ribbed tunnel, 40 m of it, laid east along a row of the grid
    1 m north of the row's edge, scanned once (no drift): run a. Run b is the same cloud 2.1 m
    further south, cut on the same grid, so that its southern tile holds 4 m of the tunnel where
    run a's holds its southern 2 m: the rest is in run a's northern tile."""
    tmp = tmp_path_factory.mktemp("cut")
    base = get_scenario("commensurate")
    scn = replace(base, geometry=replace(base.geometry, sections=(("cutting", 12.0), ("rect", 40.0), ("cutting", 12.0)),
                                         alignment=Alignment(origin=(529990.0, 180001.0, 10.0), heading_deg=90.0)),
                  runs=base.runs[:1], drift=replace(base.drift, max_horizontal=0.01, max_vertical=0.01))
    survey_dir = generate(scn, tmp / "sim", seed=3).survey_dir
    files = sorted((survey_dir / "run_a" / "tiles").glob("*.laz"))
    parts = [read_tile(f) for f in files]
    run_a = PointTile(np.vstack([p.xyz for p in parts]), np.concatenate([p.gps_time for p in parts]),
                      np.concatenate([p.intensity for p in parts]))
    run_b = replace(second_acquisition(run_a, shift=SHIFT, noise=0.005), intensity=run_a.intensity)
    tiles = {"A": [read_header(f) for f in files], "B": _grid_tiles(run_b, tmp / "B")}
    survey = types.SimpleNamespace(runs={run: types.SimpleNamespace(tiles=t) for run, t in tiles.items()})
    options = PipelineOptions()
    pairs = with_context(find_overlaps(survey), survey, options.max_misalignment_m + CONTEXT_M)
    south = next(p for p in pairs if p.tile_a.path.name == p.tile_b.path.name == "530000_179975.laz")
    return south, options


def test_a_pair_cut_lengthwise_is_matched_against_run_as_cloud_in_the_next_tile_too(cut_lengthwise):
    """Against run a's own tile the pair's votes (the grid line's keypoints, where both runs'
    tiles end) all say 0 m across and no peak fits: ``no_overlap``. Matched again against run
    a's points in its neighbouring tiles too, the windows find run b 2.1 m across."""
    pair, options = cut_lengthwise
    reg = registry()
    stages = types.SimpleNamespace(detector=reg.create("detector", "iss"), descriptor=reg.create("descriptor", "none"),
                                   matcher=reg.create("matcher", "pair_voting"))
    kp = [detect_tile((run, tile.path, (0.0, 1e9), stages, 1.0, options.pair_part_m))
          for run, tile in ((pair.run_a, pair.tile_a), (pair.run_b, pair.tile_b))]
    offset = match_pair((pair, kp[0], kp[1], stages, options, (None, None), None)).offset
    assert offset.status in ("ok", "ambiguous", "degenerate"), offset.status
    assert offset.info["joined_tiles"] == len(pair.context_a) > 1
    np.testing.assert_allclose(offset.d[1:], -SHIFT[1:], atol=0.03)  # across and up
    if offset.status == "ok":
        assert abs(offset.d[0] + SHIFT[0]) < 0.03
    assert "1 tile pair(s) found no fit against run a's tile" in joined_tiles_note([offset])
    assert "1 of them then matched" in joined_tiles_note([offset])


@pytest.mark.parametrize("centre_along", [0.35, 3.3])
def test_a_pair_matched_about_a_centre_is_matched_within_the_window_about_it(cut_lengthwise, centre_along):
    """Matched again about the along-track chains' prediction (the pipeline's second pass,
    :func:`railtraj.alongtrack.rematch_centres`), a pair is searched within 1 m of that centre:
    about the truth (0.3 m along) it is found there; about the 3.0 m alias of the tunnel's ribs
    (1.5 m) and sleepers (0.6 m), on that alias. Across and up alike."""
    pair, options = cut_lengthwise
    reg = registry()
    stages = types.SimpleNamespace(detector=reg.create("detector", "iss"), descriptor=reg.create("descriptor", "none"),
                                   matcher=reg.create("matcher", "pair_voting").widened(1.0))
    kp = [detect_tile((run, tile.path, (0.0, 1e9), stages, 1.0, options.pair_part_m))
          for run, tile in ((pair.run_a, pair.tile_a), (pair.run_b, pair.tile_b))]
    centre = np.array([centre_along, 2.1, 0.0])
    offset = match_pair((pair, kp[0], kp[1], stages, replace(options, max_misalignment_m=1.0), (None, None),
                         centre)).offset
    assert offset.status in ("ok", "ambiguous", "degenerate"), offset.status
    np.testing.assert_allclose(offset.info["center"], centre)
    np.testing.assert_allclose(offset.d[1:], -SHIFT[1:], atol=0.03)
    assert abs(offset.d[0] - (-SHIFT[0] + round(centre_along + SHIFT[0]))) < 0.05, offset.d
