"""A fork server that runs the ``sprint-map`` command line, for the map fuzz test.

Run as ``python map_fuzz_worker.py``: it imports the CLI once, prints ``ready``, then for each
JSON line ``{"args": [...], "stdout": FILE, "stderr": FILE}`` on stdin forks a child that runs
exactly what the ``sprint-map`` console script runs (``sprint_map.cli.main.main``) with those
arguments, its output going to the two files, and replies ``{"code": ..., "signal": ...}`` once
the child is reaped. An exception escaping ``main`` is printed as Python prints it (a
``Traceback`` on stderr, exit 1), and a signal (SIGBUS, SIGSEGV) is reported as such: the child
is a real process. Forking a warmed-up process makes a command cost milliseconds instead of a
Python start-up (~0.7 s with numpy, faiss and cv2), so the fuzz can run hundreds of them.
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from typing import Any


def _child(request: dict[str, Any]) -> None:
    from sprint_map.cli.main import main

    out = os.open(str(request["stdout"]), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    err = os.open(str(request["stderr"]), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(out, 1)
    os.dup2(err, 2)
    code = 0
    try:
        main(args=[str(a) for a in request["args"]], prog_name="sprint-map")
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def serve() -> None:
    import sprint_map.cli.main  # noqa: F401  (imported once, before any fork)

    print("ready", flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            try:
                _child(request)
            finally:
                os._exit(70)
        _, status = os.waitpid(pid, 0)
        reply = {"code": os.waitstatus_to_exitcode(status),
                 "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None}
        print(json.dumps(reply), flush=True)


if __name__ == "__main__":
    serve()
