"""Exception hierarchy.

Every error the library raises on purpose derives from :class:`SprintMapError`, so a caller (and
the CLI, which turns these into a one-line ``Error: ...`` message) can catch them all at once.
Each class carries a distinct exit code for the CLI (1 is for other OS errors and for ``check``
finding violations, 2 for command-line usage errors reported by click).
"""

from __future__ import annotations

__all__ = ["ConfigError", "DescriptorShapeError", "DuplicateNameError", "EmptySequenceError",
           "IncompatibleMapError", "InputError", "InvalidDescriptorError", "ListenError", "MapCorruptError",
           "MapExistsError", "MapLockedError", "NotAMapError", "ReadOnlyMapError",
           "ReplicaLostError", "SchemaVersionError", "SprintMapError", "StorageIOError",
           "UnconnectedJoinError", "UnknownSequenceError", "UnsafeServeError"]


class SprintMapError(Exception):
    """Base class of every error raised on purpose by sprint-map.

    Raised as such only for a misuse of the API (e.g. two sequences written at once).
    """

    exit_code = 17


class NotAMapError(SprintMapError):
    """The path is missing or is not a sprint-map directory."""

    exit_code = 3


class MapExistsError(SprintMapError):
    """``create`` was asked to use a directory that already holds something."""

    exit_code = 4


class MapLockedError(SprintMapError):
    """Another process holds the map's writer lock."""

    exit_code = 5


class SchemaVersionError(SprintMapError):
    """The map was written by an unknown (usually newer) schema version."""

    exit_code = 6


class MapCorruptError(SprintMapError):
    """The map violates an invariant that opening cannot repair."""

    exit_code = 7


class DescriptorShapeError(SprintMapError):
    """Descriptors have the wrong shape, dimension or dtype for this map."""

    exit_code = 8


class InvalidDescriptorError(SprintMapError):
    """Descriptors contain NaN or Inf, or values no descriptor holds (an overflow)."""

    exit_code = 9
    #: Raised by a describer: the refused image's row among those it was given (a frame
    #: source then names its frame), and the message without the row. None / "" otherwise.
    row: int | None = None
    detail: str = ""


class DuplicateNameError(SprintMapError):
    """A sequence with this name already exists in the map."""

    exit_code = 11


class UnknownSequenceError(SprintMapError):
    """No sequence with this id (or name) exists."""

    exit_code = 12


class InputError(SprintMapError):
    """An input file (descriptors, positions, images, video) cannot be used."""

    exit_code = 13


class EmptySequenceError(InputError):
    """A sequence with no frames was given (one frame is enough: a one-frame sequence is valid)."""

    exit_code = 10


class ReadOnlyMapError(SprintMapError):
    """A write was attempted on a map opened read-only."""

    exit_code = 14


class ConfigError(SprintMapError):
    """A configuration value is invalid."""

    exit_code = 15

    def __init__(self, message: str, unknown: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        #: The options no config field has (``MapConfig.hmm.rival_reach``), when that is why.
        self.unknown = unknown


class StorageIOError(SprintMapError):
    """An operating-system I/O error (EIO, ENOSPC, ...) aborted an operation."""

    exit_code = 16


class UnsafeServeError(SprintMapError):
    """``serve`` refused an unsafe setting (a non-loopback address without a bearer token)."""

    exit_code = 18


class ListenError(SprintMapError):
    """``serve`` cannot listen on the address (in use, not an address of this host)."""

    exit_code = 19


class ReplicaLostError(SprintMapError):
    """A Ray worker the command relied on died (``--ray``: a localiser replica of ``serve``,
    whose sessions end with it; the service answers their requests 503)."""

    exit_code = 20


class IncompatibleMapError(SprintMapError):
    """Two maps cannot be joined: their descriptors (kind, dimension, model, parameters) or
    their coordinate frames differ (``join``; the message names the difference)."""

    exit_code = 21


class UnconnectedJoinError(SprintMapError):
    """``join --require-connected`` refused a join that would leave an imported drive with no
    path to what the target held (nothing was changed)."""

    exit_code = 22
