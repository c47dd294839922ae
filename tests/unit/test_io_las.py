"""LAS/LAZ tiles: round trips, the real MLS snippet, and a FormatError for every bad file."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.errors import FormatError, InputError
from railtraj.io.las import read_header, read_tile, write_tile

REAL = Path(__file__).resolve().parents[1] / "data" / "laspy_mls_snippet" / "vegetation_1_3.las"


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


def test_laz_round_trip_precision_and_header(tmp_path, make_tile):
    tile = make_tile(n=5000, seed=1)
    path = tmp_path / "t.laz"
    write_tile(path, tile, crs="EPSG:7405")
    back = read_tile(path, run_id="a")
    assert back.run_id == "a" and back.name == "t.laz" and len(back) == len(tile)
    assert np.abs(back.xyz - tile.xyz).max() <= 0.5e-3 + 1e-9
    np.testing.assert_array_equal(back.gps_time, tile.gps_time)
    np.testing.assert_array_equal(back.intensity, tile.intensity)
    head = read_header(path)
    assert head.point_format == 6 and head.version == "1.4" and head.has_gps_time
    assert head.point_count == 5000 and head.crs is not None and head.crs.to_epsg() == 7405
    np.testing.assert_allclose(head.mins, tile.xyz.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(head.maxs, tile.xyz.max(axis=0), atol=1e-3)
    np.testing.assert_array_equal(head.offsets, np.floor(tile.xyz.min(axis=0)))
    with laspy.open(path) as f:
        assert f.header.are_points_compressed
    assert _leftovers(tmp_path) == []


def test_las_suffix_writes_uncompressed(tmp_path, make_tile):
    path = tmp_path / "t.las"
    write_tile(path, make_tile(n=100))
    with laspy.open(path) as f:
        assert not f.header.are_points_compressed
    assert read_header(path).crs is None


def test_template_sets_format_scales_offsets(tmp_path, make_tile):
    tile = make_tile(n=300, seed=2)
    write_tile(tmp_path / "src.las", tile)
    tmpl = read_header(tmp_path / "src.las")
    tmpl = type(tmpl)(**{**tmpl.__dict__, "point_format": 1, "version": "1.2",
                         "scales": np.array([0.01, 0.01, 0.01]),
                         "offsets": np.array([530000.0, 180000.0, 0.0])})
    write_tile(tmp_path / "out.laz", tile, template=tmpl)
    head = read_header(tmp_path / "out.laz")
    assert head.point_format == 1 and head.version == "1.2"
    np.testing.assert_array_equal(head.scales, [0.01] * 3)
    np.testing.assert_array_equal(head.offsets, [530000.0, 180000.0, 0.0])
    back = read_tile(tmp_path / "out.laz")
    assert np.abs(back.xyz - tile.xyz).max() <= 0.005 + 1e-9


def test_gps_time_type_flag_tells_the_clock(tmp_path, make_tile):
    write_tile(tmp_path / "week.laz", make_tile(n=10, t0=552884.0))
    write_tile(tmp_path / "std.laz", make_tile(n=10, t0=4.2e8))
    for name, want in (("week", laspy.header.GpsTimeType.WEEK_TIME),
                       ("std", laspy.header.GpsTimeType.STANDARD)):
        with laspy.open(tmp_path / f"{name}.laz") as f:
            assert f.header.global_encoding.gps_time_type == want


def test_real_mls_snippet_reads():
    tile = read_tile(REAL)
    assert len(tile) == 10683
    assert 552884.889 < tile.gps_time.min() < 552884.891
    assert 552886.422 < tile.gps_time.max() < 552886.424
    head = read_header(REAL)
    assert head.point_format == 1 and head.version == "1.3" and head.point_count == 10683
    np.testing.assert_allclose(tile.xyz.min(axis=0), head.mins, atol=1e-9)


def test_chunked_read_equals_full_read(tmp_path, make_tile):
    path = tmp_path / "t.laz"
    write_tile(path, make_tile(n=10_000, seed=3))
    full = read_tile(path)
    small = read_tile(path, chunk_size=777)
    np.testing.assert_array_equal(full.xyz, small.xyz)
    np.testing.assert_array_equal(full.gps_time, small.gps_time)
    np.testing.assert_array_equal(full.intensity, small.intensity)


def test_bbox_keeps_exactly_the_points_inside(tmp_path, make_tile):
    path = tmp_path / "t.laz"
    write_tile(path, make_tile(n=10_000, seed=4))
    full = read_tile(path)
    lo = np.array([530005.0, 180010.0, -100.0])
    hi = np.array([530012.0, 180020.0, 100.0])
    part = read_tile(path, chunk_size=1000, bbox=(lo, hi))
    mask = ((full.xyz >= lo) & (full.xyz <= hi)).all(axis=1)
    assert 0 < len(part) == mask.sum() < len(full)
    np.testing.assert_array_equal(part.xyz, full.xyz[mask])
    np.testing.assert_array_equal(part.gps_time, full.gps_time[mask])
    away = read_tile(path, bbox=(lo + 1000, hi + 1000))
    assert len(away) == 0 and away.xyz.shape == (0, 3)


def test_format_without_gps_time_is_refused(tmp_path):
    hdr = laspy.LasHeader(point_format=2, version="1.2")
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    las.write(tmp_path / "f2.las")
    with pytest.raises(FormatError, match=r"point format 2 has no gps_time; .*\(1, 3, 5, 6-10\)"):
        read_tile(tmp_path / "f2.las")
    assert read_header(tmp_path / "f2.las").has_gps_time is False


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_truncated_file_is_a_format_error(tmp_path, make_tile, suffix):
    good = tmp_path / f"good{suffix}"
    write_tile(good, make_tile(n=20_000, seed=5))
    bad = tmp_path / f"bad{suffix}"
    data = good.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="truncated or corrupt") as err:
        read_tile(bad)
    assert str(bad) in str(err.value)


def test_not_a_las_file(tmp_path):
    junk = tmp_path / "junk.laz"
    junk.write_bytes(b"hello world" * 50)
    with pytest.raises(FormatError, match="junk.laz cannot be read"):
        read_header(junk)
    with pytest.raises(InputError, match="does not exist"):
        read_tile(tmp_path / "missing.laz")


def test_write_failure_leaves_nothing(tmp_path):
    tile = PointTile(xyz=np.array([[0.0, 0.0, 0.0], [5e6, 0.0, 0.0]]), gps_time=np.array([1.0, 2.0]))
    with pytest.raises(FormatError, match="do not fit LAS 32-bit"):
        write_tile(tmp_path / "t.laz", tile, offsets=(0, 0, 0), scales=(0.0001,) * 3)
    assert list(tmp_path.iterdir()) == []


def test_empty_tile_round_trip(tmp_path):
    empty = PointTile(xyz=np.zeros((0, 3)), gps_time=np.zeros(0))
    write_tile(tmp_path / "e.laz", empty)
    assert len(read_tile(tmp_path / "e.laz")) == 0
