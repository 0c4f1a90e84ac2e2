"""Prometheus metrics in the text exposition format (version 0.0.4), written by hand.

Counters, gauges and histograms with labels; observed from the event loop and from worker
threads (one lock per metric), rendered at ``GET /metrics``.
"""

from __future__ import annotations

import bisect
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from typing import TypeVar

__all__ = ["Counter", "Gauge", "Histogram", "HistogramView", "LATENCY_BUCKETS", "Labels",
           "Metrics"]

#: Latency buckets in seconds (0.5 ms .. 10 s).
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0,
                   10.0)

Labels = tuple[tuple[str, str], ...]
_M = TypeVar("_M", bound="_Metric")


def _labels(labels: Labels, extra: Iterable[tuple[str, str]] = ()) -> str:
    pairs = list(labels) + list(extra)
    if not pairs:
        return ""
    inner = ",".join(f'{k}="{_escape(v)}"' for k, v in pairs)
    return "{" + inner + "}"


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _num(value: float) -> str:
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value)) if not float(value).is_integer() else str(int(value))


class _Metric(ABC):
    """One metric family: its name, help text and the lines it renders."""

    kind = ""

    def __init__(self, name: str, help_text: str) -> None:
        self.name = name
        self.help = help_text
        self._lock = threading.Lock()

    def header(self) -> list[str]:
        return [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} {self.kind}"]

    @abstractmethod
    def render(self) -> list[str]:
        """The family's sample lines, without the header."""


class Counter(_Metric):
    """A monotonically increasing count per label set."""

    kind = "counter"

    def __init__(self, name: str, help_text: str) -> None:
        super().__init__(name, help_text)
        self._values: dict[Labels, float] = {}

    def inc(self, amount: float = 1.0, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._values[key] = self._values.get(key, 0.0) + amount

    def value(self, **labels: str) -> float:
        return self._values.get(tuple(sorted(labels.items())), 0.0)

    def render(self) -> list[str]:
        with self._lock:
            items = sorted(self._values.items()) or [((), 0.0)]
        return self.header() + [f"{self.name}{_labels(k)} {_num(v)}" for k, v in items]


class Gauge(_Metric):
    """A value read at render time from a callable (sessions open, queue depth, map size)."""

    kind = "gauge"

    def __init__(self, name: str, help_text: str, read: Callable[[], float]) -> None:
        super().__init__(name, help_text)
        self._read = read

    def render(self) -> list[str]:
        return self.header() + [f"{self.name} {_num(self._read())}"]


class Histogram(_Metric):
    """Cumulative buckets, sum and count per label set."""

    kind = "histogram"

    def __init__(self, name: str, help_text: str,
                 buckets: tuple[float, ...] = LATENCY_BUCKETS) -> None:
        super().__init__(name, help_text)
        self.buckets = tuple(sorted(buckets))
        self._series: dict[Labels, list[float]] = {}  # counts per bucket + [+Inf], sum last

    def observe(self, value: float, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        index = bisect.bisect_left(self.buckets, value)
        with self._lock:
            series = self._series.get(key)
            if series is None:
                series = self._series[key] = [0.0] * (len(self.buckets) + 2)
            series[index] += 1
            series[-1] += value

    def count(self, **labels: str) -> int:
        series = self._series.get(tuple(sorted(labels.items())))
        return int(sum(series[:-1])) if series else 0

    def render(self) -> list[str]:
        with self._lock:
            items = sorted((k, list(v)) for k, v in self._series.items())
        return self.header() + _histogram_lines(self.name, self.buckets, items)


class HistogramView(_Metric):
    """A histogram whose series another object keeps and ``read`` returns at render time:
    ``{labels: [count per bucket..., count above the last, sum]}`` (as :class:`Histogram`
    keeps them). For counts kept where taking a lock could deadlock, e.g. inside the garbage
    collector's callbacks (:class:`sprint_map.server.heap.GcPauses`)."""

    kind = "histogram"

    def __init__(self, name: str, help_text: str, buckets: tuple[float, ...],
                 read: Callable[[], dict[Labels, list[float]]]) -> None:
        super().__init__(name, help_text)
        self.buckets = tuple(buckets)
        self._read = read

    def render(self) -> list[str]:
        items = sorted((k, list(v)) for k, v in self._read().items())
        return self.header() + _histogram_lines(self.name, self.buckets, items)


def _histogram_lines(name: str, buckets: tuple[float, ...],
                     items: list[tuple[Labels, list[float]]]) -> list[str]:
    lines = []
    for key, series in items:
        running = 0.0
        for bound, n in zip(buckets + (math.inf,), series[:-1], strict=True):
            running += n
            lines.append(f"{name}_bucket{_labels(key, [('le', _num(bound))])} {_num(running)}")
        lines.append(f"{name}_sum{_labels(key)} {repr(series[-1])}")
        lines.append(f"{name}_count{_labels(key)} {_num(running)}")
    return lines


class Metrics:
    """Every metric of the service (names prefixed ``sprint_map_``)."""

    def __init__(self) -> None:
        self._all: list[_Metric] = []
        self.frames = self._add(Counter(
            "sprint_map_frames_total", "Frames answered, by result (match, no_match)."))
        self.frame_seconds = self._add(Histogram(
            "sprint_map_frame_seconds", "Time to answer a frame in the server (admission to "
            "answer, queueing included), by payload (descriptor, image)."))
        self.retrieval_seconds = self._add(Histogram(
            "sprint_map_frame_retrieval_seconds", "k-NN retrieval time per frame."))
        self.hmm_seconds = self._add(Histogram(
            "sprint_map_frame_hmm_seconds", "HMM update and decision time per frame."))
        self.requests = self._add(Counter(
            "sprint_map_http_requests_total", "HTTP requests by route and status code."))
        self.sessions = self._add(Counter(
            "sprint_map_sessions_total", "Sessions by how they ended (created, committed, "
            "discarded, expired, shutdown)."))
        self.commits = self._add(Counter(
            "sprint_map_commits_total", "Commits by result (ok, error)."))
        self.commit_seconds = self._add(Histogram(
            "sprint_map_commit_seconds", "Commit time from request to durable acknowledgement."))
        self.commit_exclusive_seconds = self._add(Histogram(
            "sprint_map_commit_exclusive_seconds", "Time a commit held frames up (LMDB "
            "transaction, index add, filter invalidation)."))
        self.edges = self._add(Counter(
            "sprint_map_edges_added_total", "Edges added to the map by commits."))
        self.rejected = self._add(Counter(
            "sprint_map_rejected_total", "Requests refused by a limit, by reason."))

    def _add(self, metric: _M) -> _M:
        self._all.append(metric)
        return metric

    def gauge(self, name: str, help_text: str, read: Callable[[], float]) -> None:
        """Register a gauge read at render time."""
        self._add(Gauge(name, help_text, read))

    def histogram_view(self, name: str, help_text: str, buckets: tuple[float, ...],
                       read: Callable[[], dict[Labels, list[float]]]) -> None:
        """Register a histogram whose series ``read`` returns at render time."""
        self._add(HistogramView(name, help_text, buckets, read))

    def render(self) -> str:
        lines: list[str] = []
        for metric in self._all:
            lines.extend(metric.render())
        return "\n".join(lines) + "\n"
