"""trajectory.csv: round trip at the promised precision and one clear error per kind of bad file."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.errors import FormatError, InputError, TrajectoryError
from railtraj.io.trajectory_csv import read_trajectory_csv, write_trajectory_csv

GOOD = "time,x,y,z,roll,pitch,heading\n1.0,10,20,30,0,0,90\n2.0,11,21,31,1,2,91\n"


def test_round_trip_preserves_values_to_format_precision(tmp_path, make_trajectory):
    traj = make_trajectory(n=300, seed=1, sd=True)
    path = tmp_path / "trajectory.csv"
    write_trajectory_csv(path, traj)
    back = read_trajectory_csv(path, run_id="a")
    assert back.run_id == "a" and len(back) == len(traj)
    assert np.abs(back.time - traj.time).max() <= 0.5e-9 + 1e-10
    assert np.abs(back.xyz - traj.xyz).max() <= 0.5e-6 + 1e-9
    assert np.abs(back.rpy - traj.rpy).max() <= 0.5e-9 + 1e-12
    assert np.abs(back.sd - traj.sd).max() <= 0.5e-6 + 1e-12
    assert path.read_text().splitlines()[0] == "time,x,y,z,roll,pitch,heading,sd_x,sd_y,sd_z"


def test_round_trip_without_sd(tmp_path, make_trajectory):
    traj = make_trajectory(n=50, seed=2, sd=False)
    path = tmp_path / "t.csv"
    write_trajectory_csv(path, traj)
    assert path.read_text().splitlines()[0] == "time,x,y,z,roll,pitch,heading"
    back = read_trajectory_csv(path)
    assert back.sd is None
    np.testing.assert_allclose(back.xyz, traj.xyz, atol=1e-6)


def test_columns_found_by_name_in_any_order(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("Heading, pitch,comment,roll,z,y,x,time,sd_z,sd_y,sd_x\n"
                    "90,2,first,1,30,20,10,1.5,0.3,0.2,0.1\n"
                    "91,3,second,4,31,21,11,2.5,0.6,0.5,0.4\n")
    t = read_trajectory_csv(path)
    np.testing.assert_array_equal(t.time, [1.5, 2.5])
    np.testing.assert_array_equal(t.xyz[0], [10, 20, 30])
    np.testing.assert_array_equal(t.rpy[1], [4, 3, 91])
    np.testing.assert_array_equal(t.sd[0], [0.1, 0.2, 0.3])


def test_partial_sd_columns_are_ignored(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("time,x,y,z,roll,pitch,heading,sd_x\n1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,1\n")
    assert read_trajectory_csv(path).sd is None


def test_missing_column_names_it_and_the_file(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("time,x,y,z,roll,pitch\n1,0,0,0,0,0\n2,0,0,0,0,0\n")
    with pytest.raises(FormatError, match=r"lacks column\(s\) heading") as err:
        read_trajectory_csv(path)
    assert str(path) in str(err.value)


def test_non_numeric_cell_names_line_and_column(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "3.0,12,abc,32,0,0,92\n")
    with pytest.raises(FormatError, match=r"line 4, column 'y': 'abc' is not a number"):
        read_trajectory_csv(path)


def test_short_row_is_reported(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "3.0,12,22\n")
    with pytest.raises(FormatError, match="line 4 has 3 cells"):
        read_trajectory_csv(path)


def test_nan_is_reported_with_row(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "3.0,12,22,nan,0,0,92\n")
    with pytest.raises(TrajectoryError, match=r"column 'z' is nan at data row 3") as err:
        read_trajectory_csv(path)
    assert str(path) in str(err.value)


def test_unsorted_times_name_the_file(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "1.5,12,22,32,0,0,92\n")
    with pytest.raises(TrajectoryError, match="not strictly increasing") as err:
        read_trajectory_csv(path)
    assert str(path) in str(err.value)


def test_header_only_and_empty_files(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("time,x,y,z,roll,pitch,heading\n")
    with pytest.raises(TrajectoryError, match="0 epochs"):
        read_trajectory_csv(path)
    path.write_text("")
    with pytest.raises(FormatError, match="an empty file"):
        read_trajectory_csv(path)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_trajectory_csv(tmp_path / "nope.csv")


def test_blank_and_comment_lines_are_skipped(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "\n# a note\n3.0,12,22,32,0,0,92\n")
    assert len(read_trajectory_csv(path)) == 3


@pytest.mark.parametrize(("cell", "shown"), [("-0.02", "-0.02"), ("0", "0.0")])
def test_sd_that_is_not_positive_is_refused_with_row_and_count(tmp_path, cell, shown):
    path = tmp_path / "t.csv"
    path.write_text("time,x,y,z,roll,pitch,heading,sd_x,sd_y,sd_z\n1.0,10,20,30,0,0,90,0.1,0.1,0.1\n"
                    f"2.0,11,21,31,1,2,91,0.1,{cell},0.1\n3.0,12,22,32,1,2,91,0.1,{cell},-1\n")
    with pytest.raises(TrajectoryError, match=rf"column 'sd_y' is {shown} at data row 2 \(time 2.0\) "
                                              r"and 2 row\(s\) in all") as err:
        read_trajectory_csv(path)
    assert "remove the three sd columns" in str(err.value) and str(path) in str(err.value)


def test_messages_show_plain_numbers(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(GOOD + "346740.519,12,22,nan,0,0,92\n")
    with pytest.raises(TrajectoryError, match=r"\(time 346740.519\)") as err:
        read_trajectory_csv(path)
    path.write_text(GOOD + "2.0,12,22,32,0,0,92\n")
    with pytest.raises(TrajectoryError, match=r"\(2.0 then 2.0\)") as err2:
        read_trajectory_csv(path)
    assert "np." not in str(err.value) + str(err2.value)
