"""The viewer's browser harness: a real ``sprint-map view`` process and a real Chromium.

For the browser tests (``tests/viewer``) and ``tools/bench_viewer.py``: :class:`ViewProcess`
starts ``sprint-map view`` on a free loopback port and reads the address it announces;
:func:`chromium` drives Debian's ``chromium`` headless through its ``chromedriver`` with
Selenium (a development dependency: ``pip install -e .[dev]``; ``apt-get install chromium
chromium-driver``), with the browser's console log kept so a test can assert it has no error.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["CHROMEDRIVER", "CHROMIUM", "ViewProcess", "chromium", "chromium_available",
           "console_errors", "wait_for"]

CHROMIUM = os.environ.get("SPRINT_MAP_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("SPRINT_MAP_CHROMEDRIVER", "/usr/bin/chromedriver")


def chromium_available() -> bool:
    """Whether Chromium, its driver and Selenium are all installed."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return False
    return all(os.access(p, os.X_OK) or shutil.which(p) for p in (CHROMIUM, CHROMEDRIVER))


class ViewProcess:
    """``sprint-map view MAP [--trace OUT] --port 0`` as a subprocess, until :meth:`stop`."""

    def __init__(self, map_path: Path, trace: Path | None = None, log: Path | None = None,
                 env: dict[str, str] | None = None) -> None:
        cmd = [sys.executable, "-c", "from sprint_map.cli.main import main; main()", "view",
               str(map_path), "--port", "0"]
        if trace is not None:
            cmd += ["--trace", str(trace)]
        self._log = open(log, "w") if log is not None else subprocess.DEVNULL  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self._log, text=True,
                                     env={**os.environ, **(env or {})})
        assert self.proc.stdout is not None
        start = time.monotonic()
        line = self.proc.stdout.readline()
        self.start_s = time.monotonic() - start
        if not line.startswith("viewing "):
            self.stop()
            raise RuntimeError(f"sprint-map view did not start: {line!r}")
        self.url = line.split(" on ", 1)[1].split()[0]

    def stop(self) -> int:
        """SIGTERM, wait, return the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(60)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        if hasattr(self._log, "close"):
            self._log.close()
        return code

    def __enter__(self) -> ViewProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@contextmanager
def chromium(width: int = 1400, height: int = 900) -> Iterator[Any]:
    """A headless Chromium WebDriver (Selenium) keeping the browser's console log."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--hide-scrollbars",
                "--force-device-scale-factor=1"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def console_errors(driver: Any) -> list[str]:
    """The console's SEVERE entries since the last call, plus errors the page caught itself
    (``window.sprintViewer.errors``: uncaught exceptions and rejected promises)."""
    logged = [e["message"] for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    caught = driver.execute_script("return (window.sprintViewer || {errors: []}).errors") or []
    return logged + [str(c) for c in caught]


def wait_for(driver: Any, script: str, timeout_s: float = 60.0) -> Any:
    """Poll ``return <script>`` in the page until it is truthy; its value."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = driver.execute_script(f"return {script}")
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{script} still false after {timeout_s} s")
        time.sleep(0.05)
