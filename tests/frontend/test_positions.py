"""Reading positions.csv: frame,x,y[,heading_deg]."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.errors import InputError
from sprint_map.frontend import read_positions


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


@pytest.mark.parametrize(("rows", "n_frames"), [(9, 4), (13, 4)])
def test_stride_with_inconsistent_row_count(tmp_path, rows, n_frames):
    text = "frame,x,y\n" + "".join(f"{i},0,0\n" for i in range(rows))
    with pytest.raises(InputError, match="stride 3"):
        read_positions(write(tmp_path, text), n_frames, stride=3)


def test_unknown_length_accepts_any_complete_file(tmp_path):
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
        ("frame,x,y\n0,1,2\n0.5,1,2\n", 2, ":3: frame must be a non-negative integer"),
        ("frame,x,y\n-1,1,2\n", 1, ":2: frame must be a non-negative integer"),
        ("# c\nframe,x,y\n0,1,2\n0,3,4\n", 2, ":4: frame 0 repeated \\(first on line 3\\)"),
        ("frame,x,y\n0,1,2\n2,3,4\n", 2, ":3: frame 2 but frame 1 is missing"),
        ("frame,x,y\n0,1,2\n1,3,4\n", 3, "2 position rows for 3 frames; expected 3 rows"),
        ("frame,x,y\n0,1,2\n1,3,4\n", 1, "2 position rows for 1 frames"),
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
