"""The progress bar of ``ingest`` and ``localize``: drawn on a terminal, silent otherwise.

The terminal case runs the real command with its stderr on a pseudo-terminal (``pty``); the
other cases give it a pipe, or ``--quiet``.
"""

from __future__ import annotations

import fcntl
import io
import os
import pty
import re
import struct
import subprocess
import sys
import termios
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.cli.progress import ProgressBar, progress_display, shows_progress

DIM = 16
FRAMES = 1000  # four batches of 256 rows: the bar is updated several times
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
CLI = [sys.executable, "-c", "from sprint_map.cli.main import main; main()"]


@pytest.fixture
def drive_and_map(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, Path]:
    """A map holding one drive, and a second noisy drive of the same places as a .npy."""
    places = rng.standard_normal((FRAMES, DIM)).astype(np.float32)
    np.save(tmp_path / "first.npy", places)
    np.save(tmp_path / "second.npy",
            (places + 0.1 * rng.standard_normal(places.shape)).astype(np.float32))
    map_path = tmp_path / "city.map"
    for args in (["init", map_path, "--dim", DIM], ["ingest", map_path, tmp_path / "first.npy"]):
        result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        assert result.exit_code == 0, result.output
    return map_path, tmp_path / "second.npy"


def _env() -> dict[str, str]:
    env = dict(os.environ, TERM="xterm-256color")
    for name in ("COLUMNS", "LINES", "NO_COLOR", "FORCE_TERMINAL", "TTY_COMPATIBLE",
                 "TTY_INTERACTIVE", "TERM_PROGRAM"):
        env.pop(name, None)
    return env


def run_cli(args: list[str], tmp_path: Path, stderr_tty: bool) -> tuple[int, str, str]:
    """Run the CLI in a subprocess: (exit code, stdout, stderr with escape codes removed).

    With ``stderr_tty`` its stderr is a 24 x 100 pseudo-terminal, read until the child
    closes it; otherwise a pipe. stdout goes to a file (never a terminal). It runs in
    ``tmp_path``, so relative source names keep the bar's label short.
    """
    out_path = tmp_path / "stdout.txt"
    with open(out_path, "wb") as out:
        if not stderr_tty:
            proc = subprocess.run(CLI + args, stdout=out, stderr=subprocess.PIPE, env=_env(),
                                  timeout=300, cwd=tmp_path)
            code, err = proc.returncode, proc.stderr
        else:
            master, slave = pty.openpty()
            fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
            child = subprocess.Popen(CLI + args, stdout=out, stderr=slave, env=_env(),
                                     cwd=tmp_path)
            os.close(slave)
            chunks = []
            while True:
                try:
                    data = os.read(master, 65536)
                except OSError:  # EIO: every end of the terminal's slave side is closed
                    break
                if not data:
                    break
                chunks.append(data)
            os.close(master)
            code, err = child.wait(timeout=300), b"".join(chunks)
    return code, out_path.read_text(), ANSI.sub("", err.decode("utf-8", "replace"))


@pytest.mark.parametrize("command, label", [("ingest", "ingesting"), ("localize", "localising")])
def test_a_terminal_gets_a_bar_with_count_rate_and_eta(drive_and_map, tmp_path, command, label):
    map_path, drive = drive_and_map
    code, out, err = run_cli([command, str(map_path), str(drive)], tmp_path, stderr_tty=True)
    assert code == 0, err
    last = [line for line in re.split(r"[\r\n]+", err) if label in line][-1]
    assert "━" in last, last  # the bar
    assert f"{FRAMES}/{FRAMES}" in last and re.search(r"[\d,]+ frames/s", last), last
    assert re.search(r"eta \d+:\d\d:\d\d", last), last
    assert out.strip()  # the result still goes to stdout


@pytest.mark.parametrize("stderr_tty, extra", [(False, []), (True, ["--quiet"]), (True, ["-q"])])
def test_silent_without_a_terminal_or_with_quiet(drive_and_map, tmp_path, stderr_tty, extra):
    map_path, drive = drive_and_map
    code, out, err = run_cli(["ingest", str(map_path), str(drive), *extra], tmp_path, stderr_tty)
    assert code == 0
    assert err.strip() == ""
    assert out.startswith("added sequence 1 (second)")


class _FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_unknown_total_shows_the_count_and_rate_without_eta():
    stream = _FakeTerminal()
    bar = ProgressBar("ingesting", stream)
    for done in (256, 512, 700):
        bar(done, None)  # a video: its length is known only at its end
    bar.close()
    bar.close()  # idempotent
    last = ANSI.sub("", stream.getvalue()).rstrip().splitlines()[-1]
    assert "700/?" in last and re.search(r"[\d,]+ frames/s", last) and "eta" not in last


def test_a_bar_ends_at_its_total_so_the_next_drive_gets_its_own_line():
    stream = _FakeTerminal()
    first, second = ProgressBar("ingesting a", stream), ProgressBar("ingesting b", stream)
    for done in (256, 300):
        first(done, 300)
    assert not first.live  # ended at its total: no live line left behind
    first(300, 300)  # a late call draws nothing
    for done in (100, 200):
        second(done, 200)
    second.close()
    text = ANSI.sub("", stream.getvalue())
    assert "ingesting a" not in text[text.index("ingesting b"):]  # a ended before b began
    assert re.search(r"ingesting a \S+ 300/300", text)
    assert re.search(r"ingesting b \S+ 200/200", text)


def test_several_drives_on_a_terminal_each_end_their_bar(drive_and_map, tmp_path):
    map_path, drive = drive_and_map
    other = tmp_path / "third.npy"
    np.save(other, np.load(drive)[::-1].copy())
    code, out, err = run_cli(["ingest", str(map_path), drive.name, other.name], tmp_path,
                             stderr_tty=True)
    assert code == 0, err
    finals = [line for line in re.split(r"[\r\n]+", err) if f"{FRAMES}/{FRAMES}" in line]
    assert any(f"ingesting {drive.name} " in line for line in finals), err[-2000:]
    assert any(f"ingesting {other.name} " in line for line in finals), err[-2000:]
    assert f"ingesting {drive.name} " not in err[err.index(f"ingesting {other.name} "):]
    assert out.count("added sequence") == 2


def test_no_bar_object_without_a_terminal_or_when_quiet():
    assert not shows_progress(io.StringIO())
    assert not shows_progress(_FakeTerminal(), quiet=True)
    assert shows_progress(_FakeTerminal())
    with progress_display("x", stream=io.StringIO()) as progress:
        assert progress is None
    with progress_display("x", quiet=True, stream=_FakeTerminal()) as progress:
        assert progress is None
    stream = _FakeTerminal()
    with progress_display("x", stream=stream) as progress:
        assert isinstance(progress, ProgressBar)
    assert stream.getvalue() == ""  # nothing drawn for work that never started


def test_importing_the_cli_does_not_import_rich():
    code = "import sys, sprint_map.cli.main; print('rich' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"


def test_the_work_after_the_last_frame_has_a_line_of_its_own():
    """Once the bar is full, the phase that follows (smoothing, merge, commit) is shown with
    its elapsed time until the command closes it, or the next drive's bar draws."""
    stream = _FakeTerminal()
    first = ProgressBar("ingesting a", stream, after="smoothing and merging")
    second = ProgressBar("ingesting b", stream, after="smoothing and merging")
    first(300, 300)
    assert first.live  # the phase line, after the full bar
    second(100, 200)  # the next drive: the phase of the first is over
    assert not first.live and second.live
    second(200, 200)
    second.close()
    assert not second.live
    text = ANSI.sub("", stream.getvalue())
    assert re.search(r"ingesting a \S+ 300/300", text)
    assert re.search(r"smoothing and merging \d:\d\d:\d\d", text), text[-500:]
    assert text.index("smoothing and merging") < text.index("ingesting b")


def test_ingest_on_a_terminal_shows_its_smoothing_and_merge(drive_and_map, tmp_path):
    map_path, drive = drive_and_map
    code, out, err = run_cli(["ingest", str(map_path), str(drive)], tmp_path, stderr_tty=True)
    assert code == 0, err
    assert f"{FRAMES}/{FRAMES}" in err
    assert re.search(r"smoothing and merging \d:\d\d:\d\d", err), err[-1000:]
    assert out.startswith("added sequence 1 (second)")
