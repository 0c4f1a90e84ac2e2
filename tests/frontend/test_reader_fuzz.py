"""Seeded fuzz of the readers of outside files: bags (ROS 1, ROS 2 sqlite3 and MCAP, zstd
compressed), bare MCAP files and positions CSV files (issue 52).

Small pristine inputs (``tests/helpers/bags.py``: 4 frames, fixes) are damaged by seeded mutations:
bits flipped, a run of bytes overwritten, the file cut short, a span deleted or inserted, and
a little-endian length written at a random offset or, for MCAP, at a record's own length
field (``2**64 - 1``, ``2**62``, ``2**32 - 1``, twice the file, ...); positions files also by
lines (a field of 200,000 characters, ``nan``, ``1e309``, a BOM, a quote, a NUL, a repeated or
far frame, a line dropped or doubled). Each is read in a forked child of a warmed-up server
(``tests/helpers/reader_fuzz_worker.py``) as ``ingest`` reads it. Promises:

- no crash: the read succeeds or fails with the package's own error, never another;
- no hang: every read ends within :data:`TIMEOUT_S` seconds;
- bounded memory: the child's peak RSS grows by at most ``MEMORY_FACTOR`` times the input's
  size plus :data:`MEMORY_BASE_KB` (decoding and describing 4 frames);
- a read that succeeds is whole: one descriptor row, thumbnail and position per kept frame.

``SPRINT_MAP_FUZZ_CASES`` sets the cases per pristine input (CI: :data:`CI_CASES`, 2,010 in
all, ~50 s of CPU on one core; e.g. 1000 for a soak). Counts print with ``-s``.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.helpers.bags import drive_spec, write_bag  # noqa: E402

WORKER = Path(__file__).parents[1] / "helpers" / "reader_fuzz_worker.py"
CASES = int(os.environ.get("SPRINT_MAP_FUZZ_CASES", "0")) or None
#: Cases per pristine input in CI: 7 bags x 30 + 2 positions files x 900 = 2,010 (a bag read
#: costs ~0.15 s, most of it rosbags building its types; a positions file ~10 ms).
CI_CASES = {"bag": 30, "positions": 900}
TIMEOUT_S = 20.0
MEMORY_FACTOR = 16
MEMORY_BASE_KB = 48 * 1024
LENGTHS = (2**64 - 1, 2**63, 2**62, 2**40, 2**32 - 1, 2**31, 0)


class Worker:
    """The client of a ``reader_fuzz_worker.py`` fork server."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, str(WORKER)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdout.readline() == "ready\n"

    def __call__(self, **request: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(request | {"timeout": TIMEOUT_S}, default=str) + "\n")
        self.proc.stdin.flush()
        reply: dict[str, Any] = json.loads(self.proc.stdout.readline())
        return reply

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    client = Worker()
    yield client
    client.close()


# --- mutations of bytes --------------------------------------------------------------------

def _mcap_length_fields(data: bytes) -> list[int]:
    """Offsets of the top-level MCAP records' uint64 length fields (after the magic)."""
    out, at = [], 8
    while at + 9 <= len(data):
        out.append(at + 1)
        (length,) = struct.unpack_from("<Q", data, at + 1)
        at += 9 + length
    return out


def _pick(rng: np.random.Generator, values: tuple[int, ...]) -> int:
    """One of ``values``, exactly (``rng.choice`` would make them floats)."""
    return values[int(rng.integers(0, len(values)))]


def mutate_bytes(data: bytes, rng: np.random.Generator, mcap: bool) -> bytes:
    """One seeded damage of ``data`` (module notes)."""
    b = bytearray(data)
    n = len(b)
    how = int(rng.integers(0, 7 if mcap else 6))
    if how == 0:  # bits flipped
        for at in rng.integers(0, n, int(rng.integers(1, 17))).tolist():
            b[at] ^= 1 << int(rng.integers(0, 8))
    elif how == 1:  # a run overwritten
        at, size = int(rng.integers(0, n)), int(rng.integers(1, 65))
        b[at:at + size] = rng.bytes(size)
    elif how == 2:  # cut short
        del b[int(rng.integers(0, n)):]
    elif how == 3:  # a span deleted
        at = int(rng.integers(0, n))
        del b[at:at + int(rng.integers(1, 257))]
    elif how == 4:  # bytes inserted
        at = int(rng.integers(0, n))
        b[at:at] = rng.bytes(int(rng.integers(1, 65)))
    elif how == 5 or not (fields := _mcap_length_fields(data)):  # a length anywhere
        value = _pick(rng, LENGTHS + (2 * n,)) if rng.random() < 0.9 else n
        at = int(rng.integers(0, max(1, n - 8)))
        width = 8 if rng.random() < 0.5 else 4
        b[at:at + width] = (value % 2 ** (8 * width)).to_bytes(width, "little")
    else:  # a record's own length
        at = int(rng.choice(fields))
        b[at:at + 8] = _pick(rng, LENGTHS + (2 * n, n)).to_bytes(8, "little")
    return bytes(b)


# --- mutations of positions lines ----------------------------------------------------------

_TOKENS = ("nan", "inf", "-inf", "1e309", "9" * 400, "-1", "0.5", "1e18", '"', '"1,2"', "\x00",
           "\ufeff", "", " ", "x", "1_000", "0x10", "٣")


def mutate_lines(text: str, rng: np.random.Generator) -> str:
    """One seeded damage of a positions file, by lines and fields."""
    lines = text.splitlines(keepends=True)
    i = int(rng.integers(0, len(lines)))
    how = int(rng.integers(0, 8))
    if how == 0:  # a field replaced
        fields = lines[i].rstrip("\n").split(",")
        fields[int(rng.integers(0, len(fields)))] = str(rng.choice(_TOKENS))
        lines[i] = ",".join(fields) + "\n"
    elif how == 1:
        lines[i] = lines[i].rstrip("\n") + "," + "7" * 200_000 + "\n"
    elif how == 2:
        del lines[i]
    elif how == 3:
        lines.insert(i, lines[i])
    elif how == 4:  # a far or negative frame
        fields = lines[i].split(",")
        fields[0] = str(_pick(rng, (10**9, 10**18, -5, 40, 2**63)))
        lines[i] = ",".join(fields)
    elif how == 5:
        lines.insert(0, "\ufeff" if rng.random() < 0.5 else "# comment\r\n")
    elif how == 6:  # the header's columns changed
        lines[0] = str(rng.choice(["frame,lat,lon\n", "frame,x,y,x\n", "Frame , Y,X\n",
                                   "frame,x,y,heading_deg,sigma_m,extra\n", "frame;x;y\n"]))
    else:
        return mutate_bytes(text.encode(), rng, mcap=False).decode("utf-8", "replace") \
            if rng.random() < 0.5 else text[: int(rng.integers(0, len(text)))]
    return "".join(lines)


# --- the pristine inputs --------------------------------------------------------------------

def _bag_inputs(root: Path) -> dict[str, Path]:
    """Each kind of bag the readers take, small: 4 frames, fixes around them."""
    root.mkdir()
    out = {}
    for kind in ("ros1", "ros2-sqlite3", "ros2-mcap", "mcap"):
        out[kind] = write_bag(root / kind, kind, drive_spec(4, size=(24, 32),
                                                            image_connections=2))
    out["raw-mcap"] = write_bag(root / "raw", "mcap",
                                drive_spec(4, size=(16, 16), compressed=False))
    out["zstd-mcap"] = write_bag(root / "zstd", "ros2-mcap",
                                 drive_spec(4, size=(24, 32), compression="storage"))
    out["zstd-message"] = write_bag(root / "zmsg", "ros2-sqlite3",
                                    drive_spec(4, size=(24, 32), compression="message"))
    return out


def _storage(path: Path, rng: np.random.Generator) -> Path:
    """The file of a bag to damage: the bag file, or (mostly) a ROS 2 folder's storage."""
    if path.is_file():
        return path
    files = sorted(path.iterdir())
    storage = [p for p in files if p.name != "metadata.yaml"]
    return path / "metadata.yaml" if rng.random() < 0.1 else storage[0]


def _positions_text(rng: np.random.Generator, geographic: bool) -> str:
    rows = [f"{i},{59.9 + i * 1e-4:.6f},{10.7:.6f},{i * 3},1.5" if geographic else
            f"{i},{i * 2.5},{-i},{i * 3},1.5" for i in range(12)]
    header = "frame,lat,lon,heading_deg,sigma_m" if geographic else "frame,x,y,heading_deg,sigma_m"
    return header + "\n" + "\n".join(rows) + "\n"


def _cases(kind: str) -> int:
    return CASES or CI_CASES[kind]


def _check(case: str, reply: dict[str, Any], size: int, failures: list[str]) -> None:
    if reply["outcome"] in ("crash", "hang", "signal"):
        failures.append(f"{case}: {reply['outcome']}: {reply['error']}")
    limit = MEMORY_BASE_KB + MEMORY_FACTOR * size // 1024
    if reply["grown_kb"] > limit:
        failures.append(f"{case}: peak RSS grew {reply['grown_kb']} KB > {limit} KB")
    if reply["outcome"] == "refused" and ("\n" in reply["error"] or not reply["error"]):
        failures.append(f"{case}: not one line: {reply['error']!r}")


def _run(kind: str, names: list[str], make: Callable[[str, int], tuple[Path, dict[str, Any]]],
         worker: Worker) -> tuple[Counter[str], list[str]]:
    counts: Counter[str] = Counter()
    failures: list[str] = []
    for name in names:
        for i in range(_cases(kind)):
            path, request = make(name, i)
            size = sum(p.stat().st_size for p in ([path] if path.is_file() else path.iterdir()))
            reply = worker(path=str(path), kind=kind, **request)
            counts[reply["outcome"]] += 1
            _check(f"{kind}:{name}:{i}", reply, size, failures)
    return counts, failures


def test_damaged_bags_are_read_or_refused(tmp_path, worker):
    pristine = _bag_inputs(tmp_path / "pristine")
    for path in pristine.values():  # warm the server: one-off costs are not a case's
        worker(path=str(path), kind="bag", warm=True)
    for name, path in pristine.items():  # the pristine inputs read
        assert worker(path=str(path), kind="bag")["outcome"] == "ok", name
    work = tmp_path / "case"

    def make(name: str, i: int) -> tuple[Path, dict[str, Any]]:
        rng = np.random.default_rng([52, i, len(name), sum(map(ord, name))])
        source = pristine[name]
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        target = work / source.name
        (shutil.copytree if source.is_dir() else shutil.copy)(source, target)
        victim = _storage(target, rng)
        data = victim.read_bytes()
        victim.write_bytes(mutate_bytes(data, rng, mcap=data[:5] == b"\x89MCAP"))
        return target, {}

    counts, failures = _run("bag", sorted(pristine), make, worker)
    print(f"\nbag fuzz: {dict(counts)}")
    assert not failures, "\n".join(failures[:20])
    assert counts["refused"] > counts["ok"] / 4  # the damage was seen, and reported


def test_damaged_positions_are_read_or_refused(tmp_path, worker):
    def make(name: str, i: int) -> tuple[Path, dict[str, Any]]:
        rng = np.random.default_rng([52, 11, i, name == "geographic"])
        text = _positions_text(rng, name == "geographic")
        for _ in range(int(rng.integers(1, 4))):
            text = mutate_lines(text, rng)
        path = tmp_path / "positions.csv"
        path.write_text(text, encoding="utf-8", errors="surrogateescape")
        return path, {"frames": 12}

    counts, failures = _run("positions", ["geographic", "planar"], make, worker)
    print(f"\npositions fuzz: {dict(counts)}")
    assert not failures, "\n".join(failures[:20])
    assert counts["ok"] and counts["refused"]
