"""Opening a bag's files for ``rosbags`` so that no input can hang, exhaust memory or escape.

A bag is outside input: any byte of it may be wrong. :func:`open_reader` hands ``rosbags``
(the ``[ros]`` extra) a :class:`BagPath`, the reader-path protocol ``rosbags`` accepts in
place of a :class:`~pathlib.Path`, which

* opens only **regular files** (a FIFO would block the open forever, a link to ``/dev/zero``
  would be read forever): a ``.bag``/``.mcap``/``.db3`` file, and every file of a ROS 2 bag
  folder, are checked before anything is opened;
* reads through :class:`BoundedFile`: a read never asks for more bytes than the file holds
  from where it stands, so a record length of ``2**62`` or ``2**64 - 1`` read from a damaged
  header cannot allocate it (the read is short, and ``rosbags`` reports a truncated record);
* gives its suffix in lower case, so ``DRIVE.BAG`` and ``drive.MCAP`` are read as what they
  are (``rosbags`` tells the formats apart by the suffix, in lower case).

:func:`reading` turns any exception ``rosbags`` (and the sqlite, zstd, lz4 and bz2 libraries
under it) raises into one :class:`BagReadError` naming the bag, the topic when one is being
read, and what went wrong. Cost: one ``stat`` per file; reads are the file object's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from sprint_map.errors import InputError, SprintMapError
from sprint_map.util.validation import regular_file

__all__ = ["INSTALL_HINT", "BagPath", "BagReadError", "BoundedFile", "check_bag_files",
           "open_reader", "reading"]

INSTALL_HINT = 'bags need the ros extra: pip install "sprint-map[ros]"'


class BagReadError(InputError):
    """A bag that cannot be read (corrupt, truncated, not a bag, not a regular file)."""


def check_bag_files(path: Path) -> None:
    """Refuse a bag that is not made of regular files: a bag file that is not one, or a ROS 2
    bag folder holding an entry that is neither a regular file nor a folder (``rosbags``
    would block opening a FIFO). O(entries of the folder).

    Raises
    ------
    BagReadError
    """
    try:
        if path.is_dir():
            regular_file(path / "metadata.yaml", "a ROS 2 bag's metadata.yaml")
            for entry in sorted(path.iterdir()):
                if not entry.is_dir():
                    regular_file(entry, "a file of a ROS 2 bag folder")
        else:
            regular_file(path, "a bag")
    except BagReadError:
        raise
    except InputError as exc:
        raise BagReadError(str(exc)) from None
    except OSError as exc:
        raise BagReadError(f"{path}: cannot read bag ({exc.strerror or exc})") from None


class BoundedFile:
    """A binary file opened for reading whose ``read(n)`` returns at most the bytes left
    before the end the file had when opened: a length read from damaged data cannot make
    a read allocate more than the file's size. Everything else is the file's own."""

    def __init__(self, raw: IO[bytes], size: int) -> None:
        self._raw = raw
        self._size = size

    def read(self, size: int | None = -1) -> bytes:
        left = max(0, self._size - self._raw.tell())
        return self._raw.read(left if size is None or size < 0 else min(size, left))

    def read1(self, size: int = -1) -> bytes:
        return self.read(size)

    def readline(self, size: int | None = -1) -> bytes:
        left = max(0, self._size - self._raw.tell())
        return self._raw.readline(left if size is None or size < 0 else min(size, left))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._raw, name)

    def __enter__(self) -> BoundedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._raw.close()


class BagPath(type(Path())):  # type: ignore[misc]  # PosixPath or WindowsPath
    """A path as ``rosbags`` reads it (module notes): regular files only, every binary read
    bounded by the file's size, the suffix in lower case. Paths derived from it (``/``,
    ``parent``) are :class:`BagPath` too."""

    @property
    def suffix(self) -> str:
        return str(super().suffix).lower()

    def open(self, mode: str = "r", *args: Any, **kwargs: Any) -> Any:  # noqa: ANN401
        if any(c in mode for c in "wax+"):
            return super().open(mode, *args, **kwargs)
        size = regular_file(self, "a file of a bag")
        handle = super().open(mode, *args, **kwargs)
        return BoundedFile(handle, size) if "b" in mode else handle


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, MemoryError) or not text:
        text = f"{type(exc).__name__} {text}".strip()
    return text[:200]


@contextlib.contextmanager
def reading(path: Path, topic: str | None = None, message: int | None = None
            ) -> Iterator[None]:
    """Map every exception of the block, but the package's own errors, to one
    :class:`BagReadError` ``"<bag>: topic '<topic>'[: message <n>]: cannot read bag
    (<reason>)"``."""
    try:
        yield
    except SprintMapError:
        raise
    except Exception as exc:  # noqa: BLE001  (outside input: whatever its parsers raise)
        where = str(path) if topic is None else f"{path}: topic {topic!r}"
        if message is not None:
            where += f": image message {message}"
        raise BagReadError(f"{where}: cannot read bag ({_reason(exc)})") from None


def open_reader(path: Path) -> Any:
    """An open ``rosbags`` ``AnyReader`` of ``path`` (close it with ``reader.close()``), its
    files opened as :class:`BagPath` (module notes).

    Raises
    ------
    InputError
        ``rosbags`` is not installed; :class:`BagReadError`: the bag is not made of regular
        files, or cannot be opened.
    """
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(f"{path}: {INSTALL_HINT}") from None
    check_bag_files(path)
    with reading(path):
        reader = AnyReader([BagPath(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    return reader
