"""Survey folder discovery, trajectory loading, overlaps from tile headers, control points."""

from __future__ import annotations

import itertools
from pathlib import Path

import laspy
import numpy as np
import pytest

from railtraj.errors import FormatError, NoOverlapError, SurveyError
from railtraj.io.las import TileHeader
from railtraj.io.las import write_tile as _write_tile
from railtraj.io.sbet import trajectory_to_sbet, write_sbet
from railtraj.io.survey import (
    find_overlaps,
    in_parts,
    open_survey,
    read_control,
    require_overlaps,
    with_context,
)
from railtraj.io.trajectory_csv import write_trajectory_csv

GRID_DIR = None  # the Ordnance Survey grids railtraj installs itself (railtraj.crs)
E0, N0 = 530000.0, 180000.0


def _run(root, run_id, traj, tiles, make_tile, sbet=False):
    """Write one run folder; ``tiles`` lists (x offset, y offset) of 25 m tiles from E0, N0."""
    folder = root / run_id
    if sbet:
        write_sbet(folder / "trajectory.sbet", trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR))
    else:
        write_trajectory_csv(folder / "trajectory.csv", traj)
    for k, (dx, dy) in enumerate(tiles):
        tile = make_tile(n=200, seed=k, origin=(E0 + dx, N0 + dy, 10.0), size=25.0)
        _write_tile(folder / "tiles" / f"{int(E0 + dx)}_{int(N0 + dy)}.laz", tile)
    return folder


@pytest.fixture
def survey_dir(tmp_path, make_trajectory, make_tile):
    root = tmp_path / "survey"
    _run(root, "run_b", make_trajectory(seed=2, run_id="run_b"), [(10, 0), (35, 0)], make_tile)
    _run(root, "run-a", make_trajectory(seed=1, run_id="run-a"), [(0, 0), (25, 0)], make_tile)
    (root / "notes").mkdir()
    (root / "control.csv").write_text("id,x,y,z,sd_x,sd_y,sd_z\nGCP1,530001,180002,10.5,0.01,0.01,0.02\n"
                                      '"GCP,2",530030,180003,11,0.01,0.01,0.02\n')
    return root


def test_open_survey_discovers_runs_tiles_and_control(survey_dir, make_trajectory):
    s = open_survey(survey_dir)
    assert list(s.runs) == ["run-a", "run_b"]
    a = s.runs["run-a"]
    assert a.trajectory_path == survey_dir / "run-a" / "trajectory.csv" and a.smrmsg_path is None
    assert [t.name for t in a.tiles] == ["530000_180000.laz", "530025_180000.laz"]
    assert all(isinstance(t, TileHeader) and t.point_count == 200 for t in a.tiles)
    assert s.control_path == survey_dir / "control.csv"
    traj = s.load_trajectory("run-a")
    assert traj.run_id == "run-a"
    np.testing.assert_allclose(traj.xyz, make_trajectory(seed=1).xyz, atol=1e-6)
    with pytest.raises(SurveyError, match="no run 'c'; its runs are: run-a, run_b"):
        s.load_trajectory("c")


def test_overlaps_from_header_bounds(survey_dir):
    pairs = find_overlaps(open_survey(survey_dir))
    got = {(p.tile_a.name, p.tile_b.name) for p in pairs}
    assert got == {("530000_180000.laz", "530010_180000.laz"),
                   ("530025_180000.laz", "530010_180000.laz"),
                   ("530025_180000.laz", "530035_180000.laz")}
    assert all(p.run_a == "run-a" and p.run_b == "run_b" for p in pairs)
    first = next(p for p in pairs if p.tile_a.name.startswith("530000"))
    # x overlap is [b.min_x, a.max_x]; z spans both tiles' heights.
    assert first.overlap_min[0] == first.tile_b.mins[0]
    assert first.overlap_max[0] == first.tile_a.maxs[0]
    assert first.overlap_min[2] == min(first.tile_a.mins[2], first.tile_b.mins[2])
    assert first.overlap_max[2] == max(first.tile_a.maxs[2], first.tile_b.maxs[2])
    # the a1-b0 overlap is ~10 m wide in x; the others ~15 m
    assert len(find_overlaps(open_survey(survey_dir), min_overlap_m=12.0)) == 2


def _header(mins, maxs, name="t.laz"):
    return TileHeader(Path(name), 10, np.asarray(mins, float), np.asarray(maxs, float),
                      np.full(3, 0.001), np.zeros(3), 6, "1.4", True)


def test_overlaps_match_a_brute_force_check(survey_dir):
    rng = np.random.default_rng(7)
    s = open_survey(survey_dir)
    runs = {}
    for r in ("a", "b", "c"):
        lo = rng.uniform(0, 100, (15, 3))
        hi = lo + rng.uniform(0.5, 30, (15, 3))
        tiles = [_header(m, x) for m, x in zip(lo, hi, strict=True)]
        runs[r] = type(s.runs["run-a"])(r, survey_dir, survey_dir, tiles)
    fake = type(s)(survey_dir, runs)
    margin, min_m = 0.7, 2.0
    got = {(p.run_a, p.run_b, id(p.tile_a), id(p.tile_b)) for p in find_overlaps(fake, margin, min_m)}
    want = set()
    for ra, rb in itertools.combinations("abc", 2):
        for ta in runs[ra].tiles:
            for tb in runs[rb].tiles:
                wx = min(ta.maxs[0], tb.maxs[0]) - max(ta.mins[0], tb.mins[0]) + 2 * margin
                wy = min(ta.maxs[1], tb.maxs[1]) - max(ta.mins[1], tb.mins[1]) + 2 * margin
                if wx >= min_m and wy >= min_m:
                    want.add((ra, rb, id(ta), id(tb)))
    assert got == want and len(want) > 5


def test_margin_makes_touching_tiles_overlap(survey_dir):
    s = open_survey(survey_dir)
    a = _header([0, 0, 0], [10, 10, 1])
    b = _header([10.5, 0, 0], [20, 10, 1])
    run = type(s.runs["run-a"])
    fake = type(s)(survey_dir, {"a": run("a", survey_dir, survey_dir, [a]),
                                "b": run("b", survey_dir, survey_dir, [b])})
    assert find_overlaps(fake) == []
    with pytest.raises(NoOverlapError, match="runs a, b share no overlapping tiles"):
        require_overlaps(find_overlaps(fake), fake)
    pairs = find_overlaps(fake, margin=1.0)
    assert len(pairs) == 1
    np.testing.assert_allclose(pairs[0].overlap_min[:2], [9.5, -1.0])
    np.testing.assert_allclose(pairs[0].overlap_max[:2], [11.0, 11.0])


def test_read_control(survey_dir):
    c = read_control(survey_dir / "control.csv")
    assert len(c) == 2 and list(c.ids) == ["GCP1", "GCP,2"]
    np.testing.assert_array_equal(c.xyz[0], [530001, 180002, 10.5])
    np.testing.assert_array_equal(c.sd[1], [0.01, 0.01, 0.02])
    (survey_dir / "bad.csv").write_text("id,x,y,z,sd_x,sd_y,sd_z\nG,1,2,3,0,0.1,0.1\n")
    with pytest.raises(SurveyError, match="positive number"):
        read_control(survey_dir / "bad.csv")
    (survey_dir / "bad.csv").write_text("id,x,y,z,sd_x,sd_y,sd_z\nG,1,two,3,1,1,1\n")
    with pytest.raises(FormatError, match="column 'y': 'two' is not a number"):
        read_control(survey_dir / "bad.csv")


def test_bad_survey_paths(tmp_path):
    with pytest.raises(SurveyError, match="does not exist"):
        open_survey(tmp_path / "nope")
    (tmp_path / "f").write_text("")
    with pytest.raises(SurveyError, match="is a file, not a folder"):
        open_survey(tmp_path / "f")
    with pytest.raises(SurveyError, match=r"found 0 runs; a survey needs 2 or more"):
        open_survey(tmp_path)


def test_one_run_is_not_a_survey(tmp_path, make_trajectory, make_tile):
    _run(tmp_path, "a", make_trajectory(), [(0, 0)], make_tile)
    with pytest.raises(SurveyError, match=r"found 1 run \(a\); a survey needs 2 or more run "
                                          r"folders each with trajectory.csv and tiles/\*.laz"):
        open_survey(tmp_path)


def test_run_without_tiles_or_trajectory(tmp_path, make_trajectory, make_tile):
    _run(tmp_path, "a", make_trajectory(), [(0, 0)], make_tile)
    folder = _run(tmp_path, "b", make_trajectory(), [], make_tile)
    with pytest.raises(SurveyError, match=f"run folder {folder} has no tiles"):
        open_survey(tmp_path)
    _write_tile(folder / "tiles" / "x.las", make_tile(n=10))
    (folder / "trajectory.csv").unlink()
    with pytest.raises(SurveyError, match=f"run folder {folder} has no trajectory.csv"):
        open_survey(tmp_path)
    (folder / "trajectory.csv").write_text("")
    (folder / "trajectory.sbet").write_bytes(b"")
    with pytest.raises(SurveyError, match="has both trajectory.csv and trajectory.sbet"):
        open_survey(tmp_path)


def test_bad_run_name_and_tile_without_gps_time(tmp_path, make_trajectory, make_tile):
    _run(tmp_path, "a", make_trajectory(), [(0, 0)], make_tile)
    _run(tmp_path, "b c", make_trajectory(), [(0, 0)], make_tile)
    with pytest.raises(SurveyError, match="may contain only letters, digits"):
        open_survey(tmp_path)
    (tmp_path / "b c").rename(tmp_path / "b")
    las = laspy.LasData(laspy.LasHeader(point_format=2, version="1.2"))
    las.x = las.y = las.z = np.arange(3.0)
    las.write(tmp_path / "b" / "tiles" / "zz.las")
    with pytest.raises(FormatError, match="zz.las: point format 2 has no gps_time"):
        open_survey(tmp_path)


def test_sbet_run_loads_with_smrmsg(tmp_path, make_trajectory, make_tile):
    from railtraj.io.sbet import SMRMSG_DTYPE, write_smrmsg
    traj = make_trajectory(seed=3)
    _run(tmp_path, "a", make_trajectory(seed=1), [(0, 0)], make_tile)
    folder = _run(tmp_path, "b", traj, [(0, 0)], make_tile, sbet=True)
    smr = np.zeros(2, dtype=SMRMSG_DTYPE)
    smr["time"] = traj.span
    smr["east_rms"], smr["north_rms"], smr["down_rms"] = 0.02, 0.03, 0.05
    write_smrmsg(folder / "trajectory.smrmsg", smr)
    s = open_survey(tmp_path)
    assert s.runs["b"].smrmsg_path == folder / "trajectory.smrmsg"
    back = s.load_trajectory("b", grid_dir=GRID_DIR)
    assert np.abs(back.xyz - traj.xyz).max() < 1e-3
    assert np.abs(back.rpy - traj.rpy).max() < 1e-9
    np.testing.assert_allclose(back.sd[0], [0.02, 0.03, 0.05])


def test_a_large_overlap_is_cut_into_parts_that_tile_it(survey_dir):
    s = open_survey(survey_dir)
    run = type(s.runs["run-a"])
    a, b = _header([0, 0, 5], [50, 50, 9]), _header([10, 0, 4], [60, 28, 8])
    fake = type(s)(survey_dir, {"a": run("a", survey_dir, survey_dir, [a]),
                                "b": run("b", survey_dir, survey_dir, [b])})
    whole = find_overlaps(fake)
    assert in_parts(whole, 0.0) is whole
    parts = in_parts(whole, 25.0)  # overlap 40 x 28 m: 2 x 1 parts (28 m is within 1.2 x 25)
    lo, hi = np.array([p.overlap_min for p in parts]), np.array([p.overlap_max for p in parts])
    assert len(parts) == 2 and all(p.tile_a is a and p.tile_b is b for p in parts)
    np.testing.assert_allclose((hi - lo)[:, :2], [[20.0, 28.0], [20.0, 28.0]])
    np.testing.assert_allclose(lo.min(axis=0), whole[0].overlap_min)
    np.testing.assert_allclose(hi.max(axis=0), whole[0].overlap_max)
    assert np.isclose(np.prod((hi - lo)[:, :2], axis=1).sum(), np.prod((whole[0].overlap_max - whole[0].overlap_min)[:2]))
    kept = in_parts(whole, 50.0)  # within 1.2 x part_m: kept whole
    assert len(kept) == 1 and kept[0] is whole[0]


def test_a_pair_reads_its_runs_tiles_near_its_box_as_context(survey_dir):
    """Run a's tiles that come within the reach of the pair's box (its own, the next along the
    x axis) are where its context is read; a tile 10 m beyond is not."""
    s = open_survey(survey_dir)
    run = type(s.runs["run-a"])
    a = [_header([x, 0, 0], [x + 25, 25, 5], f"a{x}.laz") for x in (0, 25, 60)]
    b = [_header([1, 0, 0], [26, 25, 5], "b.laz")]
    fake = type(s)(survey_dir, {"a": run("a", survey_dir, survey_dir, a), "b": run("b", survey_dir, survey_dir, b)})
    pairs = with_context(find_overlaps(fake), fake, reach=5.0)
    first = next(p for p in pairs if p.tile_a is a[0])
    assert first.context_a == (Path("a0.laz"), Path("a25.laz")) and first.context_b == (Path("b.laz"),)
