"""Property-based fuzzing of the readers: any bytes give a result or railtraj's one-line error.

Every reader of user files (trajectory.csv, SBET, SMRMSG, control.csv, LAS/LAZ headers and
tiles) is fed random bytes and near-valid files (valid ones with mutated bytes, truncated,
rows shuffled, values replaced by NaN/inf/negative/huge/tiny numbers). The property: the reader
returns, or raises a :class:`RailtrajError` whose message is one line without numpy reprs;
never another exception. Examples are derandomized and bounded so the file runs in seconds.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from railtraj.data import PointTile
from railtraj.errors import RailtrajError
from railtraj.io.las import read_header, read_tile, write_tile
from railtraj.io.sbet import (
    SBET_DTYPE,
    SMRMSG_DTYPE,
    read_sbet,
    read_smrmsg,
    sbet_to_trajectory,
)
from railtraj.io.survey import read_control
from railtraj.io.trajectory_csv import read_trajectory_csv

DATA = Path(__file__).resolve().parents[1] / "data"
LAS = DATA / "laspy_mls_snippet" / "vegetation_1_3.las"
SBET = DATA / "pdal_sbet_smrmsg" / "2-points.sbet"
SMRMSG = DATA / "pdal_sbet_smrmsg" / "smrmsg.smrmsg"

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])
NUMPY_REPR = re.compile(r"\bnp\.\w+\(|\bnumpy\.\w+\(|array\(|dtype\(")


def check_message(err: Exception) -> str:
    """Assert ``err`` is railtraj's one-line error (other exceptions fail the test as they are)."""
    if not isinstance(err, RailtrajError):
        raise err
    msg = str(err)
    assert msg and "\n" not in msg and "\r" not in msg, f"multi-line error: {msg!r}"
    assert not NUMPY_REPR.search(msg), f"numpy repr in error: {msg!r}"
    return msg


def outcome(read, path: Path, data: bytes):
    """Write ``data`` to ``path`` and read it: the result, or None after checking the error,
    which must also name the file."""
    path.write_bytes(data)
    try:
        return read(path)
    except RailtrajError as err:
        msg = check_message(err)
        assert str(path) in msg, f"error does not name the file: {msg!r}"
        return None


# ----------------------------------------------------------------------------- generic bytes

@st.composite
def mutated(draw, base: bytes, max_edits: int = 4) -> bytes:
    """``base`` with a few byte edits: overwrite, insert, delete a run, or truncate."""
    data = bytearray(base)
    for _ in range(draw(st.integers(1, max_edits))):
        kind = draw(st.sampled_from(("set", "insert", "delete", "truncate")))
        pos = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "set" and data:
            data[pos] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "delete":
            del data[pos:pos + draw(st.integers(1, 16))]
        else:
            del data[pos:]
    return bytes(data)


SPECIAL = (float("nan"), float("inf"), float("-inf"), 0.0, -0.0, -1.0, 1e308, -1e308, 5e-324,
           1e-300, 2.0**63, -(2.0**63), 1e30)
special_floats = st.one_of(st.sampled_from(SPECIAL), st.floats(allow_nan=True, allow_infinity=True))


# ----------------------------------------------------------------------------- trajectory.csv

TRAJ_COLS = ("time", "x", "y", "z", "roll", "pitch", "heading")
SD_COLS = ("sd_x", "sd_y", "sd_z")


def _valid_rows(n: int) -> list[list[float]]:
    rng = np.random.default_rng(n)
    return [[552000.0 + 0.01 * i, 530000.0 + i, 180000.0 + i, 20.0,
             *rng.normal(0, 1, 2).tolist(), 30.0, *rng.uniform(0.01, 0.05, 3).tolist()]
            for i in range(n)]


def _csv(header: list[str], rows: list[list[str]]) -> bytes:
    return ("\n".join([",".join(header), *(",".join(r) for r in rows)]) + "\n").encode()


VALID_TRAJ = _csv([*TRAJ_COLS, *SD_COLS], [[repr(v) for v in r] for r in _valid_rows(12)])

cell_text = st.one_of(
    special_floats.map(repr),
    st.integers(-(10**400), 10**400).map(str),
    st.sampled_from(("", " ", "nan", "-inf", "1e999", "0x1p3", "1_000", '"1.5"', "1,5", "1.5.2",
                     "\u0661", "\x00", "#", "  7  ", "+.5", "\ufeff1")),
    st.text(max_size=4),
)


@st.composite
def near_valid_trajectory(draw) -> bytes:
    """Real columns in any order, a few rows of numbers (special values among them), the rows
    maybe shuffled, short or long, the odd cell replaced by text."""
    sd = draw(st.booleans())
    cols = [*TRAJ_COLS, *(SD_COLS if sd else ())]
    if draw(st.booleans()):
        cols.append("comment")
    header = draw(st.permutations(cols))
    n = draw(st.integers(0, 6))
    rows = []
    for r in _valid_rows(n):
        values = dict(zip((*TRAJ_COLS, *SD_COLS), r, strict=True), comment="c")
        row = [repr(values[c]) if c != "comment" else "c" for c in header]
        for _ in range(draw(st.integers(0, 2))):
            k = draw(st.integers(0, len(row) - 1))
            row[k] = draw(st.one_of(special_floats.map(repr), cell_text))
        if draw(st.integers(0, 9)) == 0:
            row = row[:draw(st.integers(0, len(row)))]
        rows.append(row)
    if draw(st.booleans()):
        rows = draw(st.permutations(rows))
    return _csv(list(header), rows)


def _read_traj(path):
    traj = read_trajectory_csv(path, run_id="r")
    assert len(traj) >= 2 and np.isfinite(traj.xyz).all() and (np.diff(traj.time) > 0).all()
    return traj


@FUZZ
@given(data=st.one_of(st.binary(max_size=300),
                      st.binary(max_size=100).map(lambda b: b",".join(
                          c.encode() for c in TRAJ_COLS) + b"\n" + b),
                      mutated(VALID_TRAJ), near_valid_trajectory()))
@example(data=VALID_TRAJ)
@example(data=b"\xff\xfe" + VALID_TRAJ)
def test_trajectory_csv_any_bytes(tmp_path, data):
    outcome(_read_traj, tmp_path / "trajectory.csv", data)


def test_valid_trajectory_csv_reads(tmp_path):
    assert outcome(_read_traj, tmp_path / "trajectory.csv", VALID_TRAJ) is not None


# ----------------------------------------------------------------------------- control.csv

CONTROL_COLS = ("id", "x", "y", "z", "sd_x", "sd_y", "sd_z")
VALID_CONTROL = (b"id,x,y,z,sd_x,sd_y,sd_z\nA,530001,180002,10.5,0.01,0.01,0.02\n"
                 b"B,530030,180003,11,0.01,0.01,0.02\n\"C,1\",530060,180004,12,0.02,0.02,0.03\n")


@st.composite
def near_valid_control(draw) -> bytes:
    header = list(draw(st.permutations(CONTROL_COLS)))
    rows = []
    for i in range(draw(st.integers(0, 5))):
        values = {"id": draw(st.one_of(st.just(f"P{i}"), st.sampled_from(("", "A", '"a,b"', " ")),
                                       st.text(max_size=4))),
                  "x": repr(530000.0 + i), "y": repr(180000.0 + i), "z": "10.0",
                  "sd_x": "0.01", "sd_y": "0.01", "sd_z": "0.02"}
        row = [values[c] for c in header]
        for _ in range(draw(st.integers(0, 2))):
            k = draw(st.integers(0, len(row) - 1))
            row[k] = draw(cell_text)
        rows.append(row)
    if draw(st.booleans()):
        rows = draw(st.permutations(rows))
    return _csv(header, rows)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), mutated(VALID_CONTROL), near_valid_control()))
@example(data=VALID_CONTROL)
@example(data=b"\x80")  # not UTF-8: was a UnicodeDecodeError
@example(data=b"id,x,y,z,sd_x,sd_y,sd_z\nA,\"1,2,3,1,1,1\n")
@example(data=b"id,x,y,z,sd_x,sd_y,sd_z\nA,\"" + b"1" * 140_000 + b"\n")  # csv field limit
def test_control_csv_any_bytes(tmp_path, data):
    cp = outcome(read_control, tmp_path / "control.csv", data)
    if cp is not None:
        assert len(cp) > 0 and np.isfinite(cp.xyz).all() and (cp.sd > 0).all()


# ----------------------------------------------------------------------------- SBET / SMRMSG

VALID_SBET = SBET.read_bytes()


def _sbet_with(**fields: float) -> bytes:
    rec = np.frombuffer(VALID_SBET, dtype=SBET_DTYPE).copy()
    for name, value in fields.items():
        rec[name] = value
    return rec.tobytes()
VALID_SMRMSG = SMRMSG.read_bytes()[:40 * SMRMSG_DTYPE.itemsize]


@st.composite
def record_mutations(draw, base: bytes, dtype: np.dtype) -> bytes:
    """Records with special values written into some fields, maybe shuffled or cut short."""
    rec = np.frombuffer(base, dtype=dtype).copy()
    for _ in range(draw(st.integers(0, 3))):
        i = draw(st.integers(0, len(rec) - 1))
        rec[draw(st.sampled_from(dtype.names))][i] = draw(special_floats)
    if draw(st.booleans()):
        rec = rec[draw(st.permutations(range(len(rec))))]
    data = rec.tobytes()
    if draw(st.integers(0, 3)) == 0:
        data = data[:draw(st.integers(0, len(data)))]
    return data


def _read_sbet_to_trajectory(path):
    """read_sbet, then the conversion a survey runs on it (PDAL's file is in California); the
    conversion's errors are about records, not the file, so they need not name it."""
    records = read_sbet(path)
    try:
        return sbet_to_trajectory(records, crs="EPSG:32611", run_id="r")
    except RailtrajError as err:
        check_message(err)
        return records


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), mutated(VALID_SBET),
                      record_mutations(VALID_SBET, SBET_DTYPE)))
@example(data=VALID_SBET)
@example(data=_sbet_with(lat=float("nan")))  # NaN position: was a pyproj ProjError
@example(data=_sbet_with(lat=0.0, lon=np.radians(63.0)))  # outside UTM 11N: was a ProjError
def test_sbet_any_bytes(tmp_path, data):
    outcome(_read_sbet_to_trajectory, tmp_path / "trajectory.sbet", data)


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), mutated(VALID_SMRMSG),
                      record_mutations(VALID_SMRMSG, SMRMSG_DTYPE)))
@example(data=VALID_SMRMSG)
def test_smrmsg_any_bytes(tmp_path, data):
    rec = outcome(read_smrmsg, tmp_path / "trajectory.smrmsg", data)
    if rec is not None:
        assert np.isfinite(rec["time"]).all()


# ----------------------------------------------------------------------------- LAS / LAZ

VALID_LAS = LAS.read_bytes()
#: LAS 1.0-1.4 public header fields railtraj's checks depend on: (offset, struct format).
LAS_FIELDS = {"version": (24, "<BB"), "header_size": (94, "<H"), "point_offset": (96, "<I"),
              "n_vlr": (100, "<I"), "point_format": (104, "<B"), "record_length": (105, "<H"),
              "legacy_count": (107, "<I"), "scales": (131, "<3d"), "offsets": (155, "<3d"),
              "bounds": (179, "<6d"), "n_evlr": (243, "<I")}


@pytest.fixture(scope="module")
def valid_laz(tmp_path_factory) -> bytes:
    rng = np.random.default_rng(0)
    xyz = np.array([530000.0, 180000.0, 20.0]) + rng.uniform(0, 10, (300, 3))
    tile = PointTile(xyz=xyz, gps_time=np.sort(552000.0 + rng.uniform(0, 2, 300)),
                     intensity=rng.integers(0, 65535, 300).astype(np.uint16), name="t.laz")
    path = tmp_path_factory.mktemp("laz") / "t.laz"
    write_tile(path, tile, crs="EPSG:27700")
    return path.read_bytes()


@st.composite
def las_header_mutations(draw, base: bytes) -> bytes:
    """The real tile with header fields set to odd values (counts, formats, NaN scales...)."""
    data = bytearray(base)
    for _ in range(draw(st.integers(1, 3))):
        offset, fmt = LAS_FIELDS[draw(st.sampled_from(sorted(LAS_FIELDS)))]
        size = struct.calcsize(fmt)
        if fmt.endswith("d"):
            n = int(fmt[1:-1] or 1)
            values = [draw(special_floats) for _ in range(n)]
        else:
            values = [draw(st.integers(0, 256 ** struct.calcsize("<" + c) - 1)) for c in fmt[1:]]
        data[offset:offset + size] = struct.pack(fmt, *values)
    return bytes(data)


def _read_header_and_tile(path):
    head = read_header(path)
    tile = read_tile(path, run_id="r", chunk_size=50_000)
    assert len(tile) == head.point_count
    return tile


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # laspy scaling corrupt scales (-> inf)
@FUZZ
@given(data=st.one_of(st.binary(max_size=400), mutated(VALID_LAS[:4000]), mutated(VALID_LAS),
                      las_header_mutations(VALID_LAS),
                      st.integers(0, len(VALID_LAS)).map(lambda n: VALID_LAS[:n])))
@example(data=VALID_LAS)
@example(data=VALID_LAS[:100] + struct.pack("<I", 2**32 - 1) + VALID_LAS[104:])  # was hours
def test_las_any_bytes(tmp_path, data):
    outcome(_read_header_and_tile, tmp_path / "tile.las", data)


def _with_laz_chunk_count(laz: bytes, n: int) -> bytes:
    """``laz`` with its chunk table claiming ``n`` chunks."""
    table = struct.unpack_from("<q", laz, struct.unpack_from("<I", laz, 96)[0])[0]
    return laz[:table + 4] + struct.pack("<I", n) + laz[table + 8:]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@settings(max_examples=200, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_laz_any_bytes(tmp_path, valid_laz, data):
    """Also the regressions: a corrupt LAZ chunk count made lazrs abort the whole process."""
    bad_chunks = _with_laz_chunk_count(valid_laz, 0x64000000)
    assert outcome(_read_header_and_tile, tmp_path / "chunks.laz", bad_chunks) is None
    blob = data.draw(st.one_of(mutated(valid_laz), las_header_mutations(valid_laz),
                               st.integers(0, len(valid_laz)).map(lambda n: valid_laz[:n])))
    outcome(_read_header_and_tile, tmp_path / "tile.laz", blob)
