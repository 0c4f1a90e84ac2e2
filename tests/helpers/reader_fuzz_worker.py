"""A fork server that reads one outside file per request, for the reader fuzz test.

Run as ``python reader_fuzz_worker.py``: it imports the readers once, prints ``ready``, then
for each JSON line ``{"kind": "bag" | "positions", "path": ..., "frames": N}`` on stdin forks a
child that reads the file as ``ingest`` does (a bag: ``open_source`` and every batch, with
thumbnails; positions: ``read_positions`` for ``frames`` frames, and at the source ordinals
``1, 4, 7, ...`` of them) and replies, once the child is reaped or killed, with
``{"outcome": "ok" | "refused" | "crash" | "hang" | "signal", "error": ..., "grown_kb": ...}``:
``refused`` is an error of the package's own (``SprintMapError``), ``crash`` anything else (its
traceback in ``error``), ``hang`` a child still running after ``timeout`` seconds (killed), and
``grown_kb`` how far the child's peak RSS rose above its RSS when forked. Forking a warmed-up
process makes a read cost milliseconds instead of a Python start-up; a request with
``"warm": true`` (a pristine input) is read in the server itself, so that what a first read
costs once (the decoder's and the descriptor's buffers, lazy imports) is not counted per case.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import sys
import time
import traceback
from typing import Any


def _rss_kb() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def _read(request: dict[str, Any]) -> None:
    import numpy as np

    from sprint_map.frontend.descriptors import DescriptorSpec
    from sprint_map.frontend.positions import read_positions
    from sprint_map.frontend.sources import open_source

    if request["kind"] == "positions":
        n = int(request["frames"])
        table = read_positions(request["path"], n)
        assert len(table) == n, (len(table), n)
        ordinals = np.arange(1, n, 3)
        table = read_positions(request["path"], ordinals, source_frames=n)
        assert table.frames.tolist() == ordinals.tolist()
        return
    src = open_source(request["path"], DescriptorSpec("hog"), batch_size=3, workers=1,
                      thumbnails=True)
    rows = src.read_all()
    assert len(rows) == src.count and src.thumbnails is not None
    assert len(src.thumbnails) == src.count and np.isfinite(rows).all()
    if src.positions is not None:
        assert len(src.positions) == src.count
        assert src.positions.frames.tolist() == src.ordinals.tolist()


def _child(request: dict[str, Any], out: int) -> None:
    from sprint_map.errors import SprintMapError

    start = _rss_kb()
    reply: dict[str, Any] = {"outcome": "ok", "error": None}
    try:
        _read(request)
    except SprintMapError as exc:
        reply = {"outcome": "refused", "error": str(exc)}
    except BaseException:  # noqa: BLE001  (the promise: only the package's own errors)
        reply = {"outcome": "crash", "error": traceback.format_exc()[-1500:]}
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    reply["grown_kb"] = max(0, peak - start)
    os.write(out, json.dumps(reply).encode())


def _run(request: dict[str, Any]) -> dict[str, Any]:
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read_end)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)  # libjpeg's warnings about damaged images
        try:
            _child(request, write_end)
        finally:
            os._exit(0)
    os.close(write_end)
    deadline = time.monotonic() + float(request.get("timeout", 20))
    status = None
    while status is None:
        done, code = os.waitpid(pid, os.WNOHANG)
        if done:
            status = code
        elif time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(read_end)
            return {"outcome": "hang", "error": None, "grown_kb": 0}
        else:
            time.sleep(0.002)
    data = b""
    while chunk := os.read(read_end, 65536):
        data += chunk
    os.close(read_end)
    if os.WIFSIGNALED(status) or not data:
        return {"outcome": "signal", "error": f"status {status}", "grown_kb": 0}
    reply: dict[str, Any] = json.loads(data)
    return reply


def serve() -> None:
    import cv2

    import sprint_map.frontend.bags
    import sprint_map.frontend.sources  # noqa: F401  (imported once, before any fork)

    cv2.setNumThreads(1)
    from rosbags.highlevel import AnyReader  # noqa: F401

    print("ready", flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        if request.get("warm"):  # read in the server itself: first-use costs paid before forks
            _read(request)
            print(json.dumps({"outcome": "ok", "error": None, "grown_kb": 0}), flush=True)
        else:
            print(json.dumps(_run(request)), flush=True)


if __name__ == "__main__":
    serve()
