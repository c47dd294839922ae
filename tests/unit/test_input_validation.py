"""Reader checks that turn silently wrong input into one clear error (or a note): control.csv,
empty tiles, unparsable tile CRS records and SMRMSG accuracies."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.errors import FormatError, SurveyError
from railtraj.io.las import read_header, write_tile
from railtraj.io.sbet import SMRMSG_DTYPE, read_smrmsg, write_smrmsg
from railtraj.io.survey import open_survey, read_control, unparsed_crs_note
from railtraj.io.trajectory_csv import write_trajectory_csv

HEADER = "id,x,y,z,sd_x,sd_y,sd_z\n"
GOOD = HEADER + "A,530001,180002,10.5,0.01,0.01,0.02\nB,530030,180003,11,0.01,0.01,0.02\n"


@pytest.mark.parametrize(("text", "error", "fragments"), [
    (GOOD.replace("530030", "abc"), FormatError, ("data row 2, column 'x': 'abc' is not a number",)),
    (GOOD.replace(",sd_z", "").replace(",0.02", ""), FormatError, ("lacks column(s) sd_z",)),
    (GOOD.replace("B,", "A,"), SurveyError, ("id(s) A appear more than once", "unique id")),
    (GOOD.replace("B,", ","), SurveyError, ("data row 2: the id is empty",)),
    (HEADER, SurveyError, ("no control points", "remove the file")),
    (GOOD.replace("10.5", "inf"), SurveyError, ("infinite coordinate for control point A (data row 1)",)),
    (GOOD.replace("0.01,0.01,0.02\nB", "0.01,-0.01,0.02\nB"), SurveyError,
     ("sd_y of control point A (data row 1) is -0.01", "positive number")),
])
def test_malformed_control_is_refused(tmp_path, text, error, fragments):
    path = tmp_path / "control.csv"
    path.write_text(text)
    with pytest.raises(error) as err:
        read_control(path)
    for fragment in fragments:
        assert fragment in str(err.value)
    assert str(path) in str(err.value)


def test_good_control_reads(tmp_path):
    (tmp_path / "control.csv").write_text(GOOD)
    cp = read_control(tmp_path / "control.csv")
    assert cp.ids.tolist() == ["A", "B"] and cp.xyz.shape == (2, 3)


def _survey(root, make_trajectory, make_tile, control: str | None = None):
    for k, run in enumerate(("run_a", "run_b")):
        write_trajectory_csv(root / run / "trajectory.csv", make_trajectory(seed=k, run_id=run))
        write_tile(root / run / "tiles" / "t0.laz", make_tile(n=50, seed=k))
    if control is not None:
        (root / "control.csv").write_text(control)
    return root


def test_open_survey_checks_control_before_any_work(tmp_path, make_trajectory, make_tile):
    root = _survey(tmp_path, make_trajectory, make_tile, GOOD.replace("B,", "A,"))
    with pytest.raises(SurveyError, match="more than once"):
        open_survey(root)


def test_empty_tile_is_refused_as_empty(tmp_path, make_trajectory, make_tile):
    root = _survey(tmp_path, make_trajectory, make_tile)
    empty = PointTile(xyz=np.zeros((0, 3)), gps_time=np.zeros(0), intensity=np.zeros(0, np.uint16))
    write_tile(root / "run_b" / "tiles" / "t1.laz", empty)
    with pytest.raises(FormatError, match=r"t1.laz is empty \(0 points\): remove it from tiles/"):
        open_survey(root)


def test_unparsable_crs_is_remembered_and_noted(tmp_path, make_trajectory, make_tile):
    root = _survey(tmp_path, make_trajectory, make_tile)
    assert unparsed_crs_note(open_survey(root), "EPSG:27700") is None
    path = root / "run_a" / "tiles" / "t0.laz"
    las = laspy.read(path)
    las.header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr("NOT A CRS"))
    las.header.global_encoding.wkt = True
    las.write(path)
    head = read_header(path)
    assert head.crs is None and "NOT A CRS" in head.crs_error
    note = unparsed_crs_note(open_survey(root), "EPSG:27700")
    assert note.startswith("1 tile(s) have a CRS record that cannot be parsed") and str(path) in note
    assert "EPSG:27700" in note


@pytest.mark.parametrize(("field", "value"), [("east_rms", -0.01), ("down_rms", 0.0), ("roll_rms", -1.0)])
def test_smrmsg_with_rms_that_cannot_be_is_refused(tmp_path, field, value):
    rec = np.zeros(4, dtype=SMRMSG_DTYPE)
    rec["time"] = [10.0, 11.0, 12.0, 13.0]
    for name in SMRMSG_DTYPE.names[1:]:
        rec[name] = 0.05
    write_smrmsg(tmp_path / "ok.smrmsg", rec)
    assert len(read_smrmsg(tmp_path / "ok.smrmsg")) == 4
    rec[field][2] = value
    write_smrmsg(tmp_path / "bad.smrmsg", rec)
    with pytest.raises(FormatError, match=rf"{field} is {value} at record 3 \(time 12.0\) and 1 record"):
        read_smrmsg(tmp_path / "bad.smrmsg")


def test_anchors_values():
    from railtraj.config import anchors_mode
    from railtraj.errors import ConfigError

    assert [anchors_mode(v) for v in ("auto", True, "False", "required", "off")] == [
        "auto", "true", "false", "true", "false"]
    with pytest.raises(ConfigError, match="anchors=maybe is not an option: use anchors=auto"):
        anchors_mode("maybe")
