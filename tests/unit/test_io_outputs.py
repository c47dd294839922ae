"""Output files of SPEC.md: exact columns, NaN handling, round trips through the readers."""

from __future__ import annotations

import json

import numpy as np

from railtraj.data import Ties, TileOffset
from railtraj.io.outputs import (
    ANCHOR_COLUMNS,
    read_anchors_csv,
    read_offsets_csv,
    read_ties_csv,
    write_anchors_csv,
    write_json,
    write_offsets_csv,
    write_ties_csv,
)


def _offsets():
    ok = TileOffset("a", "b", "t1.laz", "t,2.laz", d=np.array([0.012, -0.034, 0.0056]),
                    cov=np.diag([1e-6, 4e-6, 9e-6]), inliers=42, status="ok")
    bad = TileOffset("a", "c", "t1.laz", "t3.laz", status="degenerate")
    return [ok, bad]


def test_offsets_round_trip_with_nan_and_quoted_names(tmp_path):
    path = tmp_path / "offsets.csv"
    write_offsets_csv(path, _offsets())
    lines = path.read_text().splitlines()
    assert lines[0] == "run_a,run_b,tile_a,tile_b,dx,dy,dz,sd_x,sd_y,sd_z,inliers,status"
    assert lines[1] == 'a,b,t1.laz,"t,2.laz",0.012000,-0.034000,0.005600,0.001000,0.002000,0.003000,42,ok'
    assert lines[2] == "a,c,t1.laz,t3.laz,nan,nan,nan,nan,nan,nan,0,degenerate"
    cols = read_offsets_csv(path)
    assert list(cols["tile_b"]) == ["t,2.laz", "t3.laz"]
    np.testing.assert_allclose(cols["dx"], [0.012, np.nan])
    assert cols["inliers"].dtype == np.int64 and list(cols["inliers"]) == [42, 0]
    assert list(cols["status"]) == ["ok", "degenerate"]


def test_ties_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    parts = []
    for ra, rb, n in (("a", "b", 5), ("a", "c", 3)):
        parts.append(Ties(ra, rb, 552000 + rng.uniform(0, 10, n), 552100 + rng.uniform(0, 10, n),
                          rng.uniform(0, 1e5, (n, 3)) + [5e5, 1e5, 0],
                          rng.uniform(0, 1e5, (n, 3)) + [5e5, 1e5, 0], rng.uniform(0, 1, n)))
    path = tmp_path / "ties.csv"
    write_ties_csv(path, parts)
    cols = read_ties_csv(path)
    assert path.read_text().splitlines()[0] == ",".join(
        ["run_a", "run_b", "time_a", "time_b", "xa", "ya", "za", "xb", "yb", "zb", "weight"])
    assert list(cols["run_b"]) == ["b"] * 5 + ["c"] * 3
    xa = np.concatenate([p.xyz_a for p in parts])
    np.testing.assert_allclose(np.column_stack([cols["xa"], cols["ya"], cols["za"]]), xa,
                               rtol=0, atol=0.5e-6 + 1e-9)
    np.testing.assert_allclose(cols["time_b"], np.concatenate([p.time_b for p in parts]),
                               rtol=0, atol=0.5e-9 + 1e-10)
    np.testing.assert_allclose(cols["weight"], np.concatenate([p.weight for p in parts]), rtol=1e-8)


def test_empty_tables_have_a_header(tmp_path):
    write_ties_csv(tmp_path / "ties.csv", [])
    write_offsets_csv(tmp_path / "offsets.csv", [])
    assert (tmp_path / "ties.csv").read_text().count("\n") == 1
    assert len(read_ties_csv(tmp_path / "ties.csv")["xa"]) == 0
    assert len(read_offsets_csv(tmp_path / "offsets.csv")["run_a"]) == 0


def test_anchors_round_trip(tmp_path):
    rows = {c: np.array([1.0, 2.0]) for c in ANCHOR_COLUMNS}
    rows["run_id"] = np.array(["a", "b"])
    rows["lat"] = np.array([51.123456789123, 52.5])
    rows["lon"] = np.array([-0.987654321987, -1.5])
    path = tmp_path / "anchors.csv"
    write_anchors_csv(path, rows)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(ANCHOR_COLUMNS)
    assert ",51.123456789,-0.987654322," in lines[1]
    cols = read_anchors_csv(path)
    np.testing.assert_allclose(cols["lat"], rows["lat"], atol=0.5e-9)
    assert list(cols["run_id"]) == ["a", "b"]


def test_write_json_converts_numpy_and_nan(tmp_path):
    path = tmp_path / "metrics.json"
    write_json(path, {"n": np.int64(3), "x": np.float32(0.5), "bad": float("nan"),
                      "arr": np.array([1.0, np.inf]), "t": (1, 2), 5: {"p": tmp_path}})
    back = json.loads(path.read_text())
    assert back == {"n": 3, "x": 0.5, "bad": None, "arr": [1.0, None], "t": [1, 2],
                    "5": {"p": str(tmp_path)}}
