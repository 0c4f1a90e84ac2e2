"""Reading positions.csv: frame,x,y[,heading_deg][,sigma_m]."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.errors import InputError
from sprint_map.frontend import read_positions
from sprint_map.frontend.positions import gnss_fixes, stored_form


def write(tmp_path, text: str):
    path = tmp_path / "positions.csv"
    path.write_text(text)
    return path


def test_three_columns(tmp_path):
    path = write(tmp_path, "frame,x,y\n0,1.5,2\n1,3,4.25\n2,-1,0\n")
    out = read_positions(path, 3)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, [[0, 1.5, 2], [1, 3, 4.25], [2, -1, 0]])


def test_heading_any_column_order_rows_comments_and_blank_lines(tmp_path):
    text = "# drive 1\nY, Heading_Deg ,frame,x\n\n5,90,1,6\n3,0,0,4\n# end\n"
    out = read_positions(write(tmp_path, text), 2)
    np.testing.assert_array_equal(out, [[0, 4, 3, 0], [1, 6, 5, 90]])


@pytest.mark.parametrize(("rows", "n_frames"), [(10, 4), (11, 4), (12, 4), (7, 3)])
def test_stride_selects_original_frames(tmp_path, rows, n_frames):
    text = "frame,x,y\n" + "".join(f"{i},{i * 10},0\n" for i in range(rows))
    out = read_positions(write(tmp_path, text), n_frames, stride=3)
    np.testing.assert_array_equal(out[:, 0], np.arange(n_frames) * 3)
    np.testing.assert_array_equal(out[:, 1], np.arange(n_frames) * 30)


def test_stride_file_longer_than_the_drive(tmp_path):
    text = "frame,x,y\n" + "".join(f"{i},0,0\n" for i in range(13))
    with pytest.raises(InputError, match=r":14: frame 12 is beyond the drive \(4 frames kept "
                                         r"with stride 3\)"):
        read_positions(write(tmp_path, text), 4, stride=3)


@pytest.mark.parametrize("header", ["frame,x,y,sigma_m", "sigma_m,y,frame,x"])
def test_sigma_column(tmp_path, header):
    names = [n.strip() for n in header.split(",")]
    values = [{"frame": 0, "x": 1, "y": 2, "sigma_m": 0.5}, {"frame": 2, "x": 3, "y": 4,
                                                             "sigma_m": 3}]
    body = "".join(",".join(str(v[n]) for n in names) + "\n" for v in values)
    out = read_positions(write(tmp_path, header + "\n" + body), 3)
    assert out.shape == (3, 5) and np.isnan(out[:, 3]).all()  # no heading: NaN
    np.testing.assert_array_equal(out[:, 4], [0.5, np.nan, 3])
    np.testing.assert_array_equal(gnss_fixes(out), [[1, 2, 0.5], [np.nan] * 3, [3, 4, 3]])
    np.testing.assert_array_equal(stored_form(out)[[0, 2], :2], [[1, 2], [3, 4]])


def test_missing_rows_are_frames_without_a_fix(tmp_path):
    out = read_positions(write(tmp_path, "frame,x,y\n0,1,2\n3,3,4\n"), 5)
    np.testing.assert_array_equal(np.isfinite(out[:, 1]), [True, False, False, True, False])
    np.testing.assert_array_equal(out[:, 0], np.arange(5))
    assert gnss_fixes(out).shape == (5, 2)


def test_unknown_length_accepts_any_file(tmp_path):
    out = read_positions(write(tmp_path, "frame,x,y\n1,1,1\n0,0,0\n"), None)
    np.testing.assert_array_equal(out[:, 0], [0, 1])


@pytest.mark.parametrize(
    ("text", "n_frames", "message"),
    [
        ("", 1, "empty positions file"),
        ("frame,x,y\n", 1, "no position rows"),
        ("frame,x\n0,1\n", 1, r":1: bad header \(missing column\(s\) y\)"),
        ("frame,x,y,z\n0,1,2,3\n", 1, r":1: bad header \(unknown column\(s\) 'z'\)"),
        ("frame,x,x,y\n0,1,2,3\n", 1, ":1: bad header"),
        ("frame,x,y\n0,1\n", 1, ":2: expected 3 fields, got 2"),
        ("frame,x,y\n0,1,north\n", 1, ":2: y is not a number: 'north'"),
        ("frame,x,y\n0,nan,1\n", 1, ":2: x is not finite"),
        ("frame,x,y,sigma_m\n0,1,1,nan\n", 1, ":2: sigma_m is not finite"),
        ("frame,x,y,sigma_m\n0,1,1,0\n", 1, ":2: sigma_m must be > 0 metres, got 0"),
        ("frame,x,y,sigma_m\n0,1,1,-2\n", 1, ":2: sigma_m must be > 0 metres, got -2"),
        ("frame,x,y\n0,1,2\n0.5,1,2\n", 2, ":3: frame must be a non-negative integer"),
        ("frame,x,y\n-1,1,2\n", 1, ":2: frame must be a non-negative integer"),
        ("# c\nframe,x,y\n0,1,2\n0,3,4\n", 2, ":4: frame 0 repeated \\(first on line 3\\)"),
        ("frame,x,y\n0,1,2\n1,3,4\n", 1, r":3: frame 1 is beyond the drive \(1 frames\)"),
    ],
)
def test_errors_name_the_file_and_line(tmp_path, text, n_frames, message):
    path = write(tmp_path, text)
    with pytest.raises(
        InputError, match=rf"positions\.csv{'' if message.startswith(':') else '.*'}{message}"
    ):
        read_positions(path, n_frames)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(InputError, match="nope.csv"):
        read_positions(tmp_path / "nope.csv", 1)
    path = tmp_path / "binary.csv"
    path.write_bytes(b"\xff\xfe\x00frame")
    with pytest.raises(InputError, match="binary.csv"):
        read_positions(path, 1)
