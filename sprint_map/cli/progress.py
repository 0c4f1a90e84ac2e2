"""Progress display of long command-line work (``ingest``, ``localize``): a bar on a terminal.

:func:`progress_display` yields a :data:`~sprint_map.frontend.sources.ProgressCallback` that
draws one `rich <https://rich.readthedocs.io>`_ progress line on ``stream`` (stderr by default):
label, bar, frames done of the total, rate in frames/s, elapsed time and ETA. A source of
unknown length (a video) shows a pulsing bar, the count and the rate, with no ETA. It yields
``None`` (no display at all, and rich is not even imported) with ``quiet`` or when ``stream``
is not a terminal, so piped and scripted runs print nothing but their result. With ``after``
(``"smoothing and merging"``), the work that follows the last frame (the whole-drive smoothing,
the merge and the commit: seconds on a long drive) gets a line of its own once the bar is full,
a spinner and the time it has taken, until the command prints its result.

rich is imported on the first display only: ``import sprint_map.cli.main`` stays fast
(``tests/test_startup.py``).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

__all__ = ["ProgressBar", "progress_display", "shows_progress"]


def shows_progress(stream: TextIO, quiet: bool = False) -> bool:
    """Whether a progress display goes to ``stream``: not ``quiet`` and a terminal."""
    if quiet:
        return False
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class ProgressBar:
    """One rich progress line; call it as ``bar(frames_done, total_or_None)``.

    The line appears at the first call (so nothing is drawn for work that never starts) and is
    refreshed about ten times a second by rich's own thread. It ends, showing its final state,
    when ``frames_done`` reaches a known total (so that the next drive of a multi-drive ingest
    gets a line of its own, and its result is printed below a finished bar) or at
    :meth:`close`; later calls draw nothing. Cost per call O(1).

    Parameters
    ----------
    label : str
        What is being done (``"ingesting"``).
    stream : text stream
        Where the line goes; should be a terminal (see :func:`shows_progress`).
    after : str, optional
        The phase that follows the last frame (``"smoothing and merging"``): shown with a
        spinner and its elapsed time from the bar's end until :meth:`close`, or until the next
        bar draws.
    """

    #: The bar whose ``after`` phase is on screen (one live line at a time).
    _lingering: ProgressBar | None = None

    def __init__(self, label: str, stream: TextIO, after: str | None = None) -> None:
        self.label = label
        self.stream = stream
        self.after = after
        self._progress: Progress | None = None
        self._task: TaskID | None = None
        self._ended = False

    def __call__(self, done: int, total: int | None) -> None:
        if self._ended:
            return
        if self._progress is None or self._task is None:
            if ProgressBar._lingering is not None:  # the previous drive's phase is over
                ProgressBar._lingering.close()
            self._progress = _new_progress(self.stream)
            self._progress.start()
            self._task = self._progress.add_task(self.label, total=total)
        self._progress.update(self._task, completed=done, total=total)
        if total is not None and done >= total:
            self.finish()

    def finish(self) -> None:
        """The last frame is in: end the bar's line, then show the ``after`` phase, if any,
        until :meth:`close`."""
        if self._ended:
            return
        self.close()
        if self.after is not None:
            self._progress = _phase_progress(self.stream)
            self._progress.start()
            self._task = self._progress.add_task(self.after, total=None)
            ProgressBar._lingering = self

    @property
    def live(self) -> bool:
        """Whether the bar's line is being drawn (from the first call until its total or
        :meth:`close`)."""
        return self._progress is not None

    def close(self) -> None:
        """Draw the final state and end the line (idempotent)."""
        self._ended = True
        if ProgressBar._lingering is self:
            ProgressBar._lingering = None
        if self._progress is not None:
            self._progress.stop()
            self._progress = None


@contextmanager
def progress_display(label: str, quiet: bool = False, stream: TextIO | None = None,
                     after: str | None = None) -> Iterator[ProgressBar | None]:
    """A progress callback for the duration of the ``with`` block, or ``None``.

    Parameters
    ----------
    label : str
        What is being done, shown first on the line.
    quiet : bool
        No display at all (``--quiet``).
    stream : text stream, optional
        Default ``sys.stderr``. Without a terminal there, no display.
    after : str, optional
        The phase after the last frame (see :class:`ProgressBar`).

    Yields
    ------
    ProgressBar or None
        Pass it as the ``progress`` of a frame source; ``None`` means no display.
    """
    out = sys.stderr if stream is None else stream
    if not shows_progress(out, quiet):
        yield None
        return
    bar = ProgressBar(label, out, after)
    try:
        yield bar
    finally:
        bar.close()


def _new_progress(stream: TextIO) -> Progress:
    """A rich Progress writing to ``stream`` (rich imported here, on first use: ~45 ms)."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        Task,
        TextColumn,
        TimeElapsedColumn,
    )
    from rich.text import Text

    class RateColumn(ProgressColumn):
        """Frames per second, over rich's recent-samples window."""

        def render(self, task: Task) -> Any:
            speed = task.finished_speed or task.speed
            return Text("? frames/s" if speed is None else f"{speed:,.0f} frames/s")

    class EtaColumn(ProgressColumn):
        """Time left at the recent rate; nothing for a source of unknown length."""

        def render(self, task: Task) -> Any:
            if task.total is None:
                return Text("")
            left = 0.0 if task.finished else task.time_remaining
            if left is None:
                return Text("eta -:--:--")
            minutes, seconds = divmod(int(left), 60)
            hours, minutes = divmod(minutes, 60)
            return Text(f"eta {hours}:{minutes:02d}:{seconds:02d}")

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        RateColumn(),
        TimeElapsedColumn(),
        EtaColumn(),
        console=Console(file=stream),
        # sys.stdout and sys.stderr are left alone: commands print their result (and warnings)
        # after the line has ended.
        redirect_stdout=False,
        redirect_stderr=False,
    )


def _phase_progress(stream: TextIO) -> Progress:
    """A rich line for the work after the last frame: spinner, what it is, time taken."""
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    return Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                    console=Console(file=stream), redirect_stdout=False, redirect_stderr=False)
