"""Append-only descriptor shards: raw float32 rows in fixed-capacity files, memory-mapped to read.

Vertex ids are dense and descriptors are appended in vertex-id order, so vertex ``v`` lives in
shard ``v // shard_rows`` at row ``v % shard_rows``: no per-vertex location is stored. A shard
is sealed (never written again) once full. The committed row count of each shard is recorded in
LMDB; bytes past it belong to an uncommitted append and are truncated when a writer opens the
map. Readers only ever map committed rows, so they never see an append in flight.

A shard file shorter than its committed rows (cut short, deleted) lost committed data: it is
never extended with zeros and never mapped (a page past the end of a mapped file is a SIGBUS).
Every path that would (a writer's open, an append, a read) raises
:class:`~sprint_map.errors.MapCorruptError` instead; ``check`` reports it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sprint_map.errors import MapCorruptError, StorageIOError
from sprint_map.util import atomic
from sprint_map.util.arrays import Descriptors, Int64Array

__all__ = ["ROW_DTYPE", "ShardSet"]

ROW_DTYPE = np.dtype("<f4")


class ShardSet:
    """The ``shards/`` directory of a map.

    Parameters
    ----------
    directory : Path
        The ``shards/`` directory.
    dim : int
        Descriptor dimension (floats per row).
    shard_rows : int
        Rows per shard file.
    """

    def __init__(self, directory: Path, dim: int, shard_rows: int) -> None:
        self.directory = directory
        self.dim = dim
        self.shard_rows = shard_rows
        self.row_bytes = dim * ROW_DTYPE.itemsize
        self._maps: dict[int, tuple[int, np.memmap]] = {}
        #: Shards written by ``append(sync=False)`` and not yet fsynced (see :meth:`sync`).
        self._unsynced: set[int] = set()
        self._dir_unsynced = False

    def path(self, shard: int) -> Path:
        return self.directory / f"shard-{shard:06d}.f32"

    def lengths_for(self, total_rows: int) -> dict[int, int]:
        """Committed rows per shard when the map holds ``total_rows`` vertices."""
        full, rest = divmod(total_rows, self.shard_rows)
        lengths = dict.fromkeys(range(full), self.shard_rows)
        if rest:
            lengths[full] = rest
        return lengths

    def size_problem(self, shard: int, rows: int) -> str | None:
        """Why shard ``shard`` cannot hold its ``rows`` committed rows (missing, short), or
        None. One ``stat``."""
        path = self.path(shard)
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            return f"shard file {path.name} is missing ({rows} committed rows)"
        except OSError as exc:
            raise StorageIOError(f"cannot stat {path}: {exc.strerror or exc}") from exc
        want = rows * self.row_bytes
        if size < want:
            return (f"shard file {path.name} is truncated: {size} bytes, its {rows} committed "
                    f"rows take {want}")
        return None

    def verify(self, total_rows: int) -> None:
        """Refuse a map whose shard files miss committed rows (a writer's open).

        Raises
        ------
        MapCorruptError
            Naming the first shard that is missing or shorter than its committed rows.

        Notes
        -----
        One ``stat`` per shard: O(total_rows / shard_rows) (16 at 1M vertices with the default
        65,536 rows per shard), no data read.
        """
        for shard, rows in self.lengths_for(total_rows).items():
            problem = self.size_problem(shard, rows)
            if problem is not None:
                raise MapCorruptError(f"{problem}: committed descriptors are lost; refusing "
                                      "to write (see `sprint-map check`)")

    # --- recovery -------------------------------------------------------------------------
    def recover(self, total_rows: int) -> list[str]:
        """Truncate the open shard to the committed length and delete shards past it.

        Only the shard being filled and any created after it can hold uncommitted bytes, so
        this touches O(1) files however large the map is. A shard shorter than its committed
        length is never extended (that would invent zero rows). ``total_rows`` may also be a
        row past the committed end (a group dropping one of its sequences): rows before it
        written by ``append(sync=False)`` are still fsynced by the next :meth:`sync`.

        Raises
        ------
        MapCorruptError
            If the open shard is missing or shorter than its committed rows.
        StorageIOError
            If a file cannot be truncated or removed (the next writer's open tries again).
        """
        actions = []
        shard, rest = divmod(total_rows, self.shard_rows)
        # Rows past the cut are gone; rows before it written since the last sync (a group's
        # earlier sequences, when one of its sequences is dropped) still need their fsync.
        self._unsynced = {s for s in self._unsynced if s < shard or (s == shard and rest)}
        path = self.path(shard)
        if rest:
            problem = self.size_problem(shard, rest)
            if problem is not None:
                self._maps.clear()
                raise MapCorruptError(f"{problem}: committed descriptors are lost")
        try:
            if path.exists():
                if rest == 0:
                    atomic.unlink(path)
                    actions.append(f"removed uncommitted shard {path.name}")
                elif path.stat().st_size != rest * self.row_bytes:
                    atomic.truncate(path, rest * self.row_bytes)
                    actions.append(f"truncated {path.name} to {rest} committed rows")
            shard += 1
            while self.path(shard).exists():
                path = self.path(shard)
                atomic.unlink(path)
                actions.append(f"removed uncommitted shard {path.name}")
                shard += 1
            if actions:
                atomic.fsync_dir(self.directory)
                self._dir_unsynced = False  # every entry of the directory is durable now
        except OSError as exc:
            raise StorageIOError(
                f"cannot roll back descriptor shard {path.name}: {exc.strerror or exc}"
            ) from exc
        finally:
            self._maps.clear()
        return actions

    # --- writing ----------------------------------------------------------------------------
    def append(self, start_row: int, rows: Descriptors, *, sync: bool = True) -> dict[int, int]:
        """Write ``rows`` at global row ``start_row`` and fsync them (``sync=False``: later,
        by :meth:`sync`, which must run before a commit records them).

        Returns the new committed length of every shard touched, to be recorded in LMDB by the
        caller's commit. Nothing is visible to readers until that commit.

        Raises
        ------
        StorageIOError
            On any write or fsync error; the caller must roll back with :meth:`recover`.
        """
        rows = np.ascontiguousarray(rows, dtype=ROW_DTYPE)
        lengths: dict[int, int] = {}
        created = False
        done = 0
        path = self.path(start_row // self.shard_rows)
        try:
            while done < len(rows):
                row = start_row + done
                shard, offset = divmod(row, self.shard_rows)
                take = min(len(rows) - done, self.shard_rows - offset)
                path = self.path(shard)
                created |= not path.exists()
                fd = atomic.open_for_write(path)
                try:
                    if os.fstat(fd).st_size < offset * self.row_bytes:
                        # Truncating up would fill the lost committed rows with zeros.
                        raise MapCorruptError(
                            f"shard file {path.name} is shorter than its {offset} committed "
                            "rows: committed descriptors are lost; refusing to write")
                    # Drop any stale tail first, then write at the committed offset.
                    atomic.truncate(path, offset * self.row_bytes, fd)
                    view = rows[done : done + take].data.cast("B")
                    atomic.write_at(fd, path, view, offset * self.row_bytes)
                    if sync:
                        atomic.fsync(fd, path)  # a failure is final: the caller rolls back
                    else:
                        self._unsynced.add(shard)
                finally:
                    os.close(fd)
                lengths[shard] = offset + take
                done += take
            if created and sync:
                atomic.fsync_dir(self.directory)
            self._dir_unsynced |= created and not sync
        except OSError as exc:
            raise StorageIOError(
                f"cannot write descriptor shard {path.name}: {exc.strerror or exc}"
            ) from exc
        return lengths

    def sync(self) -> None:
        """fsync the shards written by ``append(sync=False)`` since the last sync (and the
        directory, if one was created): one fsync per shard touched, however many appends.

        Raises
        ------
        StorageIOError
            On an fsync error; the caller must roll back with :meth:`recover`.
        """
        path = self.directory
        try:
            for shard in sorted(self._unsynced):
                path = self.path(shard)
                atomic.fsync_file(path)
            if self._dir_unsynced:
                path = self.directory
                atomic.fsync_dir(self.directory)
        except OSError as exc:
            raise StorageIOError(f"cannot write descriptor shard {path.name}: "
                                 f"{exc.strerror or exc}") from exc
        self._unsynced.clear()
        self._dir_unsynced = False

    # --- reading ----------------------------------------------------------------------------
    def _map(self, shard: int, committed: int) -> np.memmap:
        cached = self._maps.get(shard)
        if cached is not None and cached[0] == committed:
            return cached[1]
        path = self.path(shard)
        # Never map past the end of the file: reading such a page is a SIGBUS, not an error.
        problem = self.size_problem(shard, committed)
        if problem is not None:
            raise MapCorruptError(f"{problem}: committed descriptors are lost")
        try:
            mm = np.memmap(path, dtype=ROW_DTYPE, mode="r", shape=(committed, self.dim))
        except (OSError, ValueError) as exc:
            raise StorageIOError(f"cannot map {path}: {exc}") from exc
        self._maps[shard] = (committed, mm)
        return mm

    def rows(self, start: int, stop: int, total_rows: int) -> Descriptors:
        """Rows ``start..stop-1`` (global vertex ids) of a map holding ``total_rows`` rows.

        A range inside one shard is a zero-copy read-only view of the memory map; a range that
        spans shards is copied.
        """
        if not 0 <= start <= stop <= total_rows:
            raise IndexError(f"rows {start}..{stop} outside 0..{total_rows}")
        parts = []
        row = start
        while row < stop:
            shard, offset = divmod(row, self.shard_rows)
            committed = min(self.shard_rows, total_rows - shard * self.shard_rows)
            take = min(stop - row, self.shard_rows - offset)
            parts.append(self._map(shard, committed)[offset : offset + take])
            row += take
        if not parts:
            return np.empty((0, self.dim), dtype=ROW_DTYPE)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def take(self, vertex_ids: Int64Array, total_rows: int) -> Descriptors:
        """Rows of arbitrary vertex ids (copied)."""
        out = np.empty((len(vertex_ids), self.dim), dtype=ROW_DTYPE)
        for i, vid in enumerate(np.asarray(vertex_ids, dtype=np.int64)):
            out[i] = self.rows(int(vid), int(vid) + 1, total_rows)[0]
        return out

    def close(self) -> None:
        self._maps.clear()
