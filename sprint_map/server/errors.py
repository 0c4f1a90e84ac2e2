"""HTTP errors of the service: one JSON shape, and the status of each library error.

Every error response is ``{"error": <code>, "message": <one line>}``. Bad input is always a 4xx
(the library raises a :class:`SprintMapError` subclass for it); only a bug is a 500.
"""

from __future__ import annotations

from sprint_map.errors import (
    ConfigError,
    DescriptorShapeError,
    DuplicateNameError,
    EmptySequenceError,
    IncompatibleMapError,
    InputError,
    InvalidDescriptorError,
    MapLockedError,
    NotAMapError,
    ReadOnlyMapError,
    ReplicaLostError,
    SprintMapError,
    StorageIOError,
    UnconnectedJoinError,
    UnknownSequenceError,
)

__all__ = ["ApiError", "busy", "from_library", "unknown_session"]


class ApiError(Exception):
    """An error answer: HTTP ``status``, a stable machine-readable ``code``, a message."""

    def __init__(self, status: int, code: str, message: str,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers or {}

    def body(self) -> dict[str, str]:
        return {"error": self.code, "message": self.message}


#: Library error -> (HTTP status, code); the first matching class wins (subclasses first).
_STATUS: list[tuple[type[SprintMapError], int, str]] = [
    (EmptySequenceError, 409, "empty_session"),
    (DescriptorShapeError, 422, "descriptor_shape"),
    (InvalidDescriptorError, 422, "invalid_descriptor"),
    (DuplicateNameError, 409, "duplicate_name"),
    (IncompatibleMapError, 422, "incompatible_map"),
    (UnconnectedJoinError, 409, "unconnected"),
    (NotAMapError, 422, "not_a_map"),
    (UnknownSequenceError, 404, "unknown_sequence"),
    (InputError, 422, "bad_input"),
    (ConfigError, 422, "bad_config"),
    (StorageIOError, 503, "storage_error"),
    (MapLockedError, 503, "map_locked"),
    (ReadOnlyMapError, 503, "read_only"),
    (ReplicaLostError, 503, "replica_lost"),
]


def from_library(exc: SprintMapError) -> ApiError:
    """The :class:`ApiError` for a library error (500 only for API misuse, i.e. a bug)."""
    for cls, status, code in _STATUS:
        if isinstance(exc, cls):
            return ApiError(status, code, str(exc))
    return ApiError(500, "internal", str(exc))


def unknown_session(session_id: str) -> ApiError:
    return ApiError(404, "unknown_session", f"no open session {session_id!r} (never created, "
                    "committed, discarded or expired)")


def busy(message: str) -> ApiError:
    """503 with ``Retry-After``: a bounded queue is full; the client should retry later."""
    return ApiError(503, "busy", message, {"Retry-After": "1"})
