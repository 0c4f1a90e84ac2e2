"""The LMDB environment of a map: named databases, read snapshots, retried write transactions.

LMDB is the single source of truth and its write transaction is the commit point of every change.
Durability settings are LMDB's defaults (``sync=True, metasync=True``): a committed transaction
survives SIGKILL and power loss.
"""

from __future__ import annotations

import fcntl
import os
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import lmdb

from sprint_map.errors import MapCorruptError, MapLockedError, NotAMapError, StorageIOError
from sprint_map.storage.lock import LOCK_NAME, open_lock_file

__all__ = ["CORRUPT_ERRORS", "DB_NAMES", "LmdbEnv", "MAX_DBS", "OPTIONAL_DBS", "check_data_file",
           "lock_out_writers"]

T = TypeVar("T")

#: Named databases. Keys/values are described in ``docs/architecture.md``, "On-disk format".
DB_NAMES = (
    "meta",  # ascii key -> value (schema_version, config, counters)
    "sequences",  # >I seq_id -> SequenceRecord json
    "seq_names",  # utf-8 name -> >I seq_id
    "vrange",  # >Q last vertex id of a sequence -> >I seq_id  (floor look-up vertex -> sequence)
    "vertex_data",  # >Q vertex id -> >dddd x, y, heading, timestamp (only when given)
    "edges",  # >QQ (src, dst) -> >dIId weight, query seq, frame, time
    "edges_rev",  # >QQ (dst, src) -> b""   reverse index
    "uf",  # >I seq_id -> >II parent, size       union-find over sequences
    "members",  # >I root >I member -> b""        component membership, no scan of uf
    "comp",  # >I root -> >QQ sequences, vertices per component
    "shards",  # >I shard number -> >Q committed rows
    "removed",  # >Q last vertex of a removed sequence -> >QI first vertex, seq_id (schema 2)
    "digests",  # >I seq_id -> 16-byte BLAKE2b of its descriptor rows (absent: older writer)
    "thumbnails",  # >I seq_id >I image_id -> JPEG bytes (only for drives ingested with them)
    "sightings",  # >I seq_id >I image_id -> >Idf count, last seen, distance + last drive name
    "drive_stats",  # >I seq_id -> >Q frames + dim <f4 mean descriptor (absent: older writer)
)
#: Databases a map of an older schema may lack: a writer's open creates them (the migration),
#: a reader reads such a map as if they were empty.
OPTIONAL_DBS = frozenset({"removed", "digests", "thumbnails", "sightings", "drive_stats"})
MAX_DBS = 24

#: LMDB errors that mean the file's pages are not what LMDB wrote: the corrupt-map error.
CORRUPT_ERRORS: tuple[type[lmdb.Error], ...] = (
    lmdb.CorruptedError, lmdb.PageNotFoundError, lmdb.InvalidError, lmdb.VersionMismatchError,
    lmdb.IncompatibleError)

#: LMDB's meta page (``MDB_meta`` after the 16-byte page header, 64-bit little-endian build):
#: magic, version at 16; the free DB's ``md_pad`` (the page size) at 40; last page, txnid at 136.
_META_MAGIC = 0xBEEFC0DE
_META_HEAD = struct.Struct("<II")
_META_PSIZE = struct.Struct("<I")
_META_TAIL = struct.Struct("<QQ")
_META_BYTES = 152


def check_data_file(path: Path) -> None:
    """Refuse an LMDB ``data.mdb`` shorter than its newest meta page says it is.

    LMDB memory-maps the file and trusts it: a page past the end of a truncated file is a
    SIGBUS, not an error. So before any open, the two meta pages of the file header are read
    (two 152-byte reads and an ``fstat``: O(1)) and the file must reach the last page of the
    newest valid meta (``(last_pg + 1) * page_size`` bytes). A writer only ever appends pages
    before it writes the meta that counts them, so a reader racing it never sees a file too
    short. The meta layout is LMDB's on-disk format 1 of a 64-bit build.

    Raises
    ------
    MapCorruptError
        The file is truncated, or its header is not LMDB's.
    StorageIOError
        The file cannot be read.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        raise NotAMapError(f"not a sprint-map directory (no {path})") from None
    except OSError as exc:
        raise StorageIOError(f"cannot open {path}: {exc.strerror or exc}") from exc
    try:
        first = os.pread(fd, _META_BYTES, 0)
        metas = []
        if len(first) == _META_BYTES and _META_HEAD.unpack_from(first, 16)[0] == _META_MAGIC:
            psize = _META_PSIZE.unpack_from(first, 40)[0]
            if psize < 512 or psize > 1 << 16 or psize & (psize - 1):
                raise MapCorruptError(f"LMDB file {path} is corrupt: page size {psize}")
            second = os.pread(fd, _META_BYTES, psize)
            for raw in (first, second):
                if len(raw) == _META_BYTES and _META_HEAD.unpack_from(raw, 16)[0] == _META_MAGIC:
                    last_pg, txnid = _META_TAIL.unpack_from(raw, 136)
                    metas.append((txnid, last_pg))
        # The size after the metas: a writer appending pages and then writing the meta that
        # counts them between an earlier fstat and these reads would look like a truncation.
        size = os.fstat(fd).st_size
        if not metas:
            raise MapCorruptError(f"LMDB file {path} is corrupt: no valid meta page "
                                  f"({size} bytes)")
        _, last_pg = max(metas)
        need = (last_pg + 1) * psize
        if size < need or size < 2 * psize:
            raise MapCorruptError(f"LMDB file {path} is truncated: {size} bytes, its last "
                                  f"committed page needs {max(need, 2 * psize)}")
    except OSError as exc:
        raise StorageIOError(f"cannot read {path}: {exc.strerror or exc}") from exc
    finally:
        os.close(fd)


class LmdbEnv:
    """A map's LMDB environment with its named databases opened once.

    Parameters
    ----------
    path : Path
        The ``map.lmdb`` directory.
    readonly : bool
        Open for reading only (many readers may share a map with one writer).
    map_size : int
        Initial map size for a new environment; grows by doubling on ``MapFullError``.
    create : bool
        Create the environment and its databases (only at map creation).
    map_root : Path, optional
        The map directory holding ``LOCK`` (default: the parent of ``path``; a generation
        directory's environment lives one level deeper).
    """

    def __init__(
        self, path: Path, *, readonly: bool, map_size: int = 1 << 30, create: bool = False,
        map_root: Path | None = None,
    ) -> None:
        if not create and not (path / "data.mdb").is_file():
            raise NotAMapError(f"not a sprint-map directory (no {path / 'data.mdb'})")
        if not create:
            check_data_file(path / "data.mdb")
        self.readonly = readonly
        self._broken: str | None = None
        self._reader_lock: int | None = None
        # LMDB readers register in lock.mdb, which they must be able to write. A reader that
        # cannot (a read-only map directory) reads without it, holding a shared flock on the
        # map's LOCK instead so that no writer can run meanwhile (see lock_out_writers).
        lockless = readonly and not create and not _lock_file_writable(path)
        try:
            self.env = lmdb.open(
                str(path),
                map_size=map_size,
                max_dbs=MAX_DBS,
                readonly=readonly,
                create=create,
                subdir=True,
                lock=not lockless,
                # Python threads share read transactions' slots poorly; one slot per txn.
                max_readers=256,
            )
        except CORRUPT_ERRORS as exc:
            raise MapCorruptError(f"LMDB environment {path} is corrupt: {exc}") from exc
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot open {path}: {exc}") from exc
        except (OverflowError, ValueError, TypeError) as exc:  # a map size LMDB cannot take
            raise StorageIOError(f"cannot open {path}: map size {map_size}: {exc}") from exc
        if lockless:
            try:
                self._reader_lock = lock_out_writers(map_root or path.parent)
            except BaseException:
                self.env.close()
                raise
        else:
            # A reader killed with -9 leaves a slot that pins old pages and grows the file.
            self.env.reader_check()
        self._dbs: dict[str, lmdb._Database] = {}
        if readonly:
            # Without an explicit txn py-lmdb commits its own read txn, which publishes the
            # handles to the environment (handles opened in a caller's read txn are not).
            try:
                for name in DB_NAMES:
                    try:
                        self._dbs[name] = self.env.open_db(name.encode(), create=False)
                    except lmdb.NotFoundError:
                        if name not in OPTIONAL_DBS:
                            raise
            except lmdb.NotFoundError as exc:
                self.close()
                raise NotAMapError(f"not a sprint-map directory ({path}: {exc})") from exc
            except CORRUPT_ERRORS as exc:
                self.close()
                raise MapCorruptError(f"LMDB environment {path} is corrupt: {exc}") from exc
            except lmdb.Error as exc:
                self.close()
                raise StorageIOError(f"cannot open {path}: {exc}") from exc
        else:
            # Only creation makes the databases: opening must not write into an LMDB
            # environment that is not a map.
            try:
                with self.env.begin(write=True) as txn:
                    # Required ones first: an environment that is not a map fails before the
                    # optional ones are created in it (the transaction is then aborted).
                    for name in sorted(DB_NAMES, key=lambda n: n in OPTIONAL_DBS):
                        self._dbs[name] = self.env.open_db(
                            name.encode(), txn=txn, create=create or name in OPTIONAL_DBS)
            except lmdb.NotFoundError as exc:
                self.close()
                raise NotAMapError(f"not a sprint-map directory ({path}: {exc})") from exc
            except CORRUPT_ERRORS as exc:
                self.close()
                raise MapCorruptError(f"LMDB environment {path} is corrupt: {exc}") from exc
            except lmdb.Error as exc:
                self.close()
                raise StorageIOError(f"cannot open {path}: {exc}") from exc

    def db(self, name: str) -> lmdb._Database:
        return self._dbs[name]

    def has_db(self, name: str) -> bool:
        """Whether the named database exists (an optional one may not, in an old map)."""
        return name in self._dbs

    def _usable(self) -> None:
        if self._broken is not None:
            raise StorageIOError(f"the map's LMDB environment is unusable: {self._broken}; "
                                 "reopen the map")

    @staticmethod
    @contextmanager
    def translated() -> Iterator[None]:
        """Turn LMDB errors raised in the block into ours: corruption (``MDB_CORRUPTED``, a page
        not found, ...) into MapCorruptError, any other into StorageIOError.

        For reads through a transaction held beyond its :meth:`read` block (a pinned snapshot):
        :meth:`read` only translates what is raised inside its own block.
        """
        try:
            yield
        except CORRUPT_ERRORS as exc:
            raise MapCorruptError(f"the map's LMDB is corrupt: {exc}") from exc
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot read the map's LMDB: {exc}") from exc

    @contextmanager
    def read(self) -> Iterator[lmdb.Transaction]:
        """A consistent read snapshot for the duration of the ``with`` block.

        Raises
        ------
        StorageIOError
            For any LMDB error, at the start or inside the block.
        """
        self._usable()
        try:
            try:
                txn = self.env.begin(buffers=False)
            except lmdb.MapResizedError:
                # Another process grew the map: adopt its size, then retry.
                self.env.set_mapsize(0)
                txn = self.env.begin(buffers=False)
        except CORRUPT_ERRORS as exc:
            raise MapCorruptError(f"the map's LMDB is corrupt: {exc}") from exc
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot read the map's LMDB: {exc}") from exc
        try:
            yield txn
        except CORRUPT_ERRORS as exc:
            raise MapCorruptError(f"the map's LMDB is corrupt: {exc}") from exc
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot read the map's LMDB: {exc}") from exc
        finally:
            txn.abort()

    def write(self, body: Callable[[lmdb.Transaction], T]) -> T:
        """Run ``body(txn)`` in one write transaction and commit it; retry if the map is full.

        ``body`` must do all its writes through ``txn`` and be safe to run again: on
        ``MapFullError`` the transaction is aborted, the map size doubled (with no transaction
        open in this process, as LMDB requires) and ``body`` re-run from scratch.

        Raises
        ------
        StorageIOError
            For any other LMDB error (I/O error, disk full at commit), or when the map cannot
            grow (no address space or memory for the larger map). Nothing was committed. A
            failed commit is not retried, and a map that could not grow is unusable in this
            process until reopened.

        Notes
        -----
        Each doubling re-runs ``body``: O(log(final / initial size)) runs in the worst case,
        and a commit that fills the map runs at most twice in practice. Each run first clears
        the reader slots of dead processes (O(readers), one ``kill(pid, 0)`` each): a reader
        killed during a long writer session must not pin old pages until the next open.
        """
        while True:
            self._usable()
            try:
                self.env.reader_check()
                with self.env.begin(write=True) as txn:
                    return body(txn)
            except lmdb.MapFullError:
                self._grow()
            except lmdb.MapResizedError:
                self._adopt_size()
            except CORRUPT_ERRORS as exc:
                raise MapCorruptError(f"the map's LMDB is corrupt: {exc}") from exc
            except lmdb.Error as exc:
                raise StorageIOError(f"LMDB write failed: {exc}") from exc

    def _grow(self) -> None:
        size = 0
        try:
            size = self.map_size()
            self.env.set_mapsize(size * 2)
        except lmdb.Error as exc:
            # py-lmdb closes an environment whose resize failed.
            self._broken = f"could not grow it from {size} to {size * 2} bytes ({exc})"
            raise StorageIOError(
                f"the map's LMDB is full ({size} bytes) and cannot grow to {size * 2} "
                f"bytes: {exc}; nothing was committed"
            ) from exc

    def _adopt_size(self) -> None:
        try:
            self.env.set_mapsize(0)
        except lmdb.Error as exc:
            self._broken = f"could not adopt the map's new size ({exc})"
            raise StorageIOError(f"cannot adopt the map's new LMDB size: {exc}") from exc

    def map_size(self) -> int:
        return int(self.env.info()["map_size"])

    def copy_compact(self, dest: Path) -> None:
        """Write a compacted, consistent copy of the environment into directory ``dest``."""
        self.env.copy(str(dest), compact=True)

    def close(self) -> None:
        self.env.close()
        if self._reader_lock is not None:
            os.close(self._reader_lock)  # drops the shared flock
            self._reader_lock = None


def _lock_file_writable(path: Path) -> bool:
    """Whether this process may write LMDB's lock file (or create it) in ``path``."""
    lock_file = path / "lock.mdb"
    if lock_file.exists():
        return os.access(lock_file, os.R_OK | os.W_OK)
    return os.access(path, os.W_OK)


def lock_out_writers(root: Path) -> int | None:
    """Hold a shared flock on ``root/LOCK`` so that no writer opens the map; return its fd.

    Writers take the same lock exclusively (:mod:`sprint_map.storage.lock`), so a reader that
    cannot register in LMDB's lock file is refused while a writer is at work, and a writer is
    refused while such a reader is open.
    """
    try:
        fd = open_lock_file(root / LOCK_NAME, os.O_RDONLY)
    except FileNotFoundError:
        return None  # no writer ever ran here, and none can create the lock file
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise MapLockedError(
            f"map is being written by another process and this process cannot register as an "
            f"LMDB reader (no write access to {root / 'map.lmdb' / 'lock.mdb'}); retry when "
            f"the writer is done: {root / LOCK_NAME}"
        ) from None
    return fd
