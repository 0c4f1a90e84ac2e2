"""The LMDB environment of a map: named databases, read snapshots, retried write transactions.

LMDB is the single source of truth and its write transaction is the commit point of every change.
Durability settings are LMDB's defaults (``sync=True, metasync=True``): a committed transaction
survives SIGKILL and power loss.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import lmdb

from sprint_map.errors import NotAMapError, StorageIOError

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
)
MAX_DBS = 16


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
    """

    def __init__(
        self, path: Path, *, readonly: bool, map_size: int = 1 << 30, create: bool = False
    ) -> None:
        if not create and not (path / "data.mdb").is_file():
            raise NotAMapError(f"not a sprint-map directory (no {path / 'data.mdb'})")
        try:
            self.env = lmdb.open(
                str(path),
                map_size=map_size,
                max_dbs=MAX_DBS,
                readonly=readonly,
                create=create,
                subdir=True,
                # Python threads share read transactions' slots poorly; one slot per txn.
                max_readers=256,
            )
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot open {path}: {exc}") from exc
        self.readonly = readonly
        # A reader killed with -9 leaves a slot that pins old pages and grows the file.
        self.env.reader_check()
        self._dbs: dict[str, lmdb._Database] = {}
        if readonly:
            # Without an explicit txn py-lmdb commits its own read txn, which publishes the
            # handles to the environment (handles opened in a caller's read txn are not).
            try:
                for name in DB_NAMES:
                    self._dbs[name] = self.env.open_db(name.encode(), create=False)
            except lmdb.NotFoundError as exc:
                self.env.close()
                raise NotAMapError(f"not a sprint-map directory ({path}: {exc})") from exc
        else:
            # Only creation makes the databases: opening must not write into an LMDB
            # environment that is not a map.
            try:
                with self.env.begin(write=True) as txn:
                    for name in DB_NAMES:
                        self._dbs[name] = self.env.open_db(name.encode(), txn=txn, create=create)
            except lmdb.NotFoundError as exc:
                self.env.close()
                raise NotAMapError(f"not a sprint-map directory ({path}: {exc})") from exc

    def db(self, name: str) -> lmdb._Database:
        return self._dbs[name]

    @contextmanager
    def read(self) -> Iterator[lmdb.Transaction]:
        """A consistent read snapshot for the duration of the ``with`` block."""
        try:
            txn = self.env.begin(buffers=False)
        except lmdb.MapResizedError:
            # Another process grew the map: adopt its size, then retry.
            self.env.set_mapsize(0)
            txn = self.env.begin(buffers=False)
        try:
            yield txn
        finally:
            txn.abort()

    def write(self, body: Callable[[lmdb.Transaction], T]) -> T:
        """Run ``body(txn)`` in one write transaction and commit it; retry if the map is full.

        ``body`` must do all its writes through ``txn`` and be safe to run again: on
        ``MapFullError`` the transaction is aborted, the map size doubled (with no transaction
        open in this process, as LMDB requires) and ``body`` re-run from scratch.
        """
        while True:
            try:
                with self.env.begin(write=True) as txn:
                    return body(txn)
            except lmdb.MapFullError:
                self.env.set_mapsize(self.env.info()["map_size"] * 2)
            except lmdb.MapResizedError:
                self.env.set_mapsize(0)
            except lmdb.Error as exc:
                raise StorageIOError(f"LMDB write failed: {exc}") from exc

    def map_size(self) -> int:
        return int(self.env.info()["map_size"])

    def copy_compact(self, dest: Path) -> None:
        """Write a compacted, consistent copy of the environment into directory ``dest``."""
        self.env.copy(str(dest), compact=True)

    def close(self) -> None:
        self.env.close()
