"""Reading positions.csv: frame,x,y or frame,lat,lon, [,heading_deg][,sigma_m]."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.errors import InputError
from sprint_map.frontend import read_positions
from sprint_map.frontend.positions import gnss_fixes


def write(tmp_path, text: str):
    path = tmp_path / "positions.csv"
    path.write_text(text)
    return path


def test_three_columns(tmp_path):
    path = write(tmp_path, "frame,x,y\n0,1.5,2\n1,3,4.25\n2,-1,0\n")
    out = read_positions(path, 3)
    assert out.xy.dtype == np.float64 and not out.geographic
    assert out.heading_deg is None and out.sigma_m is None
    np.testing.assert_array_equal(out.table(), [[0, 1.5, 2], [1, 3, 4.25], [2, -1, 0]])


def test_heading_any_column_order_rows_comments_and_blank_lines(tmp_path):
    text = "# drive 1\nY, Heading_Deg ,frame,x\n\n5,90,1,6\n3,0,0,4\n# end\n"
    out = read_positions(write(tmp_path, text), 2)
    np.testing.assert_array_equal(out.table(), [[0, 4, 3, 0], [1, 6, 5, 90]])


@pytest.mark.parametrize("header", ["frame,x,y,sigma_m", "frame,lat,lon,sigma_m",
                                    "sigma_m,lon,frame,lat"])
def test_sigma_column_planar_and_geographic(tmp_path, header):
    names = [n.strip() for n in header.split(",")]
    values = {0: {"frame": 0, "x": 1, "y": 2, "lat": 59.5, "lon": 10.25, "sigma_m": 0.5},
              2: {"frame": 2, "x": 3, "y": 4, "lat": 59.6, "lon": 10.5, "sigma_m": 3}}
    body = "".join(",".join(str(v[n]) for n in names) + "\n" for v in values.values())
    out = read_positions(write(tmp_path, header + "\n" + body), 3)
    assert out.geographic == ("lat" in names)
    np.testing.assert_array_equal(out.sigma_m, [0.5, np.nan, 3])
    first = ("lat", "lon") if out.geographic else ("x", "y")
    np.testing.assert_array_equal(out.xy[0], [values[0][first[0]], values[0][first[1]]])
    assert np.isnan(out.xy[1]).all()  # no row: a frame without a fix
    np.testing.assert_array_equal(out.fixed, [True, False, True])


def test_missing_rows_are_frames_without_a_fix(tmp_path):
    out = read_positions(write(tmp_path, "frame,x,y\n0,1,2\n3,3,4\n"), 5)
    np.testing.assert_array_equal(out.fixed, [True, False, False, True, False])
    rows = out.rows()
    assert rows.shape == (5, 5) and np.isnan(rows[1]).all()


@pytest.mark.parametrize(("rows", "n_frames"), [(10, 4), (11, 4), (12, 4), (7, 3)])
def test_stride_selects_original_frames(tmp_path, rows, n_frames):
    text = "frame,x,y\n" + "".join(f"{i},{i * 10},0\n" for i in range(rows))
    out = read_positions(write(tmp_path, text), n_frames, stride=3)
    np.testing.assert_array_equal(out.frames, np.arange(n_frames) * 3)
    np.testing.assert_array_equal(out.xy[:, 0], np.arange(n_frames) * 30)


def test_stride_file_longer_than_the_drive(tmp_path):
    text = "frame,x,y\n" + "".join(f"{i},0,0\n" for i in range(13))
    with pytest.raises(InputError, match=r":14: frame 12 is beyond the drive \(4 frames kept "
                                         r"with stride 3\)"):
        read_positions(write(tmp_path, text), 4, stride=3)


def test_gnss_fixes_are_x_y_sigma_of_the_stored_rows(tmp_path):
    out = read_positions(write(tmp_path, "frame,x,y,sigma_m\n0,1,2,0.5\n2,3,4,3\n"), 3)
    np.testing.assert_array_equal(gnss_fixes(out.rows()),
                                  [[1, 2, 0.5], [np.nan] * 3, [3, 4, 3]])
    plain = read_positions(write(tmp_path, "frame,x,y\n0,1,2\n3,3,4\n"), 5)
    fixes = gnss_fixes(plain.rows())
    assert fixes.shape == (5, 3) and np.isnan(fixes[:, 2]).all()  # the map's default sigma
    np.testing.assert_array_equal(np.isfinite(fixes[:, 0]), [True, False, False, True, False])


def test_unknown_length_accepts_any_file(tmp_path):
    out = read_positions(write(tmp_path, "frame,x,y\n1,1,1\n0,0,0\n"), None)
    np.testing.assert_array_equal(out.frames, [0, 1])


@pytest.mark.parametrize(
    ("text", "n_frames", "message"),
    [
        ("", 1, "empty positions file"),
        ("frame,x,y\n", 1, "no position rows"),
        ("frame,x\n0,1\n", 1, r":1: bad header \(missing column\(s\) y\)"),
        ("frame,lat\n0,1\n", 1, r":1: bad header \(missing column\(s\) lon\)"),
        ("frame,x,y,lat\n0,1,2,3\n", 1, r":1: bad header \(unknown column\(s\) 'x', 'y'\)"),
        ("frame,x,y,z\n0,1,2,3\n", 1, r":1: bad header \(unknown column\(s\) 'z'\)"),
        ("frame,x,x,y\n0,1,2,3\n", 1, ":1: bad header"),
        ("frame,x,y\n0,1\n", 1, ":2: expected 3 fields, got 2"),
        ("frame,x,y\n0,1,north\n", 1, ":2: y is not a number: 'north'"),
        ("frame,x,y\n0,nan,1\n", 1, ":2: x is not finite"),
        ("frame,x,y,sigma_m\n0,1,1,nan\n", 1, ":2: sigma_m is not finite"),
        ("frame,x,y,sigma_m\n0,1,1,0\n", 1, ":2: sigma_m must be > 0 metres, got 0"),
        ("frame,x,y,sigma_m\n0,1,1,-2\n", 1, ":2: sigma_m must be > 0 metres, got -2"),
        ("frame,lat,lon\n0,91,0\n", 1, r":2: lat 91 is outside \[-90, 90\]"),
        ("frame,lat,lon\n0,45,-180.5\n", 1, r":2: lon -180.5 is outside \[-180, 180\]"),
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


def test_a_utf8_byte_order_mark_is_skipped(tmp_path):
    # issue 52 (11): before, "unknown column '\ufeffframe'"
    path = tmp_path / "positions.csv"
    path.write_bytes("\ufeffframe,x,y\n0,1,2\n1,3,4\n".encode())
    np.testing.assert_array_equal(read_positions(path, 2).xy, [[1, 2], [3, 4]])


@pytest.mark.parametrize("where", ["header", "row"])
def test_a_field_beyond_the_csv_limit_is_one_error(tmp_path, where):
    # issue 52 (11): a field over 131,072 characters was a _csv.Error traceback
    huge = "1" * 200_000
    text = (f"frame,x,y{huge}\n0,1,2\n" if where == "header" else f"frame,x,y\n0,1,{huge}\n")
    with pytest.raises(InputError, match=rf"positions\.csv:{1 if where == 'header' else 2}: a "
                                         "field longer than 1000 characters"):
        read_positions(write(tmp_path, text), 1)


@pytest.mark.parametrize("text", ['frame,x,y\n0,1,"2\n', 'frame,x,y\n0,1,"2"3\n'])
def test_a_line_that_is_not_csv_is_one_error(tmp_path, text):
    with pytest.raises(InputError, match=r"positions\.csv:2: not a CSV line"):
        read_positions(write(tmp_path, text), 1)


def test_a_positions_file_that_is_not_a_regular_file_is_refused(tmp_path):
    # in a real process: before, a FIFO blocked for ever and /dev/zero was read for ever
    import os
    import subprocess
    import sys

    os.mkfifo(tmp_path / "fifo.csv")
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    code = ("import sys; from sprint_map.frontend import read_positions\n"
            "from sprint_map.errors import InputError\n"
            "try: read_positions(sys.argv[1], 1)\n"
            "except InputError as exc: print(exc)")
    for name, kind in (("fifo.csv", "a FIFO"), ("zero.csv", "a character device")):
        done = subprocess.run([sys.executable, "-c", code, str(tmp_path / name)],
                              capture_output=True, text=True, timeout=30)
        assert done.stdout == (f"{tmp_path / name}: positions must be a regular file, this "
                               f"is {kind}\n"), done.stderr


def test_source_ordinals_pick_their_rows(tmp_path):
    # issue 52 (5): the frames --every-m kept (1, 4, 7 of 9) get the rows of frames 1, 4, 7
    text = "frame,x,y\n" + "".join(f"{i},{i * 10},0\n" for i in range(9))
    out = read_positions(write(tmp_path, text), np.array([1, 4, 7]), source_frames=9)
    np.testing.assert_array_equal(out.frames, [1, 4, 7])
    np.testing.assert_array_equal(out.xy[:, 0], [10, 40, 70])
    gaps = read_positions(write(tmp_path, "frame,x,y\n4,1,1\n8,2,2\n"), np.array([1, 4, 7]),
                          source_frames=9)
    np.testing.assert_array_equal(gaps.fixed, [False, True, False])  # no row: no fix


@pytest.mark.parametrize(("text", "message"), [
    ("frame,x,y\n" + "".join(f"{i},0,0\n" for i in range(10)),
     r":11: frame 9 is beyond the drive \(9 frames\)"),
    ("frame,x,y\n0,0,0\n1,0,0\n2,0,0\n",
     r"rows for frames 0..2, one per kept frame, but a positions file numbers the source's "
     r"frames: 3 of its 9 were kept \(frames 1, 4, 7\)"),
])
def test_a_file_longer_than_the_source_or_one_row_per_kept_frame_is_an_error(tmp_path, text,
                                                                              message):
    with pytest.raises(InputError, match=message):
        read_positions(write(tmp_path, text), np.array([1, 4, 7]), source_frames=9)


def test_one_row_per_kept_frame_of_a_strided_source_is_an_error(tmp_path):
    text = "frame,x,y\n" + "".join(f"{i},0,0\n" for i in range(4))
    with pytest.raises(InputError, match="one per kept frame"):  # before: rows 0 and 3 taken
        read_positions(write(tmp_path, text), 4, stride=3, source_frames=10)
    whole = "frame,x,y\n" + "".join(f"{i},{i},0\n" for i in range(10))
    np.testing.assert_array_equal(read_positions(write(tmp_path, whole), 4, stride=3,
                                                 source_frames=10).xy[:, 0], [0, 3, 6, 9])
