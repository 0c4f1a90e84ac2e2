"""The map's components, persisted in LMDB: a union-find over sequences with membership lists.

A component of the map is a set of sequences joined by inter-sequence edges; its id is the
sequence id of its union-find root (so a component id can change when components merge: the
smaller one takes the id of the larger).

Three databases hold it (see :mod:`sprint_map.storage.lmdb_env`):

- ``uf``: ``seq -> (parent, size)``; ``size`` is meaningful at roots.
- ``members``: ``(root, member)`` keys, so listing a component is one prefix scan.
- ``comp``: ``root -> (sequences, vertices)`` totals, so listing all components touches one
  record per component and never the sequences.

Notes
-----
``find`` is O(alpha(n)) amortised with path compression (compression only happens in write
transactions). ``union`` is union by size and moves the smaller component's membership keys, so
a sequence's keys move O(log n) times over the life of the map: O(n log n) in total.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping

import lmdb

from sprint_map.errors import MapCorruptError
from sprint_map.storage.keys import COMP_VAL, UF_VAL, RecordStruct, read_u32, u32
from sprint_map.storage.lmdb_env import LmdbEnv

__all__ = ["MEMBER_KEY", "ComponentStore"]

MEMBER_KEY = RecordStruct(">II")


class ComponentStore:
    """The persisted union-find's operations on an open LMDB transaction of ``env``."""

    def __init__(self, env: LmdbEnv) -> None:
        self._uf = env.db("uf")
        self._members = env.db("members")
        self._comp = env.db("comp")

    def _row(self, txn: lmdb.Transaction, seq: int) -> tuple[int, int]:
        raw = txn.get(u32(seq), db=self._uf)
        if raw is None:
            raise MapCorruptError(f"sequence {seq} has no union-find record")
        parent, size = UF_VAL.unpack(raw)
        return int(parent), int(size)

    def add(self, txn: lmdb.Transaction, seq: int, n_vertices: int) -> None:
        """Make ``seq`` a new singleton component of ``n_vertices`` vertices."""
        txn.put(u32(seq), UF_VAL.pack(seq, 1), db=self._uf)
        txn.put(MEMBER_KEY.pack(seq, seq), b"", db=self._members)
        txn.put(u32(seq), COMP_VAL.pack(1, n_vertices), db=self._comp)

    def find(self, txn: lmdb.Transaction, seq: int, *, compress: bool = False) -> int:
        """Return the root (component id) of ``seq``; compress the path if ``compress``."""
        path = []
        node = seq
        parent, _ = self._row(txn, node)
        while parent != node:
            path.append(node)
            if len(path) > 1_000_000:
                raise MapCorruptError(f"union-find cycle through sequence {seq}")
            node = parent
            parent, _ = self._row(txn, node)
        if compress:
            for other in path[:-1]:  # the last one already points at the root
                _, size = self._row(txn, other)
                txn.put(u32(other), UF_VAL.pack(node, size), db=self._uf)
        return node

    def union(self, txn: lmdb.Transaction, a: int, b: int) -> int:
        """Merge the components of ``a`` and ``b``; return the surviving root."""
        ra = self.find(txn, a, compress=True)
        rb = self.find(txn, b, compress=True)
        if ra == rb:
            return ra
        _, size_a = self._row(txn, ra)
        _, size_b = self._row(txn, rb)
        if (size_a, -ra) < (size_b, -rb):  # larger wins; ties go to the smaller id
            ra, rb, size_a, size_b = rb, ra, size_b, size_a
        txn.put(u32(rb), UF_VAL.pack(ra, size_b), db=self._uf)
        txn.put(u32(ra), UF_VAL.pack(ra, size_a + size_b), db=self._uf)
        for member in self.members(txn, rb):
            txn.delete(MEMBER_KEY.pack(rb, member), db=self._members)
            txn.put(MEMBER_KEY.pack(ra, member), b"", db=self._members)
        seqs_a, verts_a = self.component_totals(txn, ra)
        seqs_b, verts_b = self.component_totals(txn, rb)
        txn.put(u32(ra), COMP_VAL.pack(seqs_a + seqs_b, verts_a + verts_b), db=self._comp)
        txn.delete(u32(rb), db=self._comp)
        return ra

    def rebuild(self, txn: lmdb.Transaction, lengths: Mapping[int, int],
                joins: Iterable[tuple[int, int]]) -> int:
        """Replace everything by the union-find of sequences ``lengths`` joined by ``joins``.

        ``lengths`` maps each sequence to its vertex count; ``joins`` are ``(seq, seq)`` pairs
        (the edges). The unions are replayed in commit order (a pair when the later of its two
        sequences was added), so the partition is the one the commits made and the roots
        (component ids) mostly theirs: the order of the unions inside one commit is not stored,
        and where a commit joined several components, another may win a tie. Returns the number
        of components.

        Notes
        -----
        O((n + J) alpha(n)) finds plus O(n log n) membership moves; used by ``check --repair``.
        """
        for db in (self._uf, self._members, self._comp):
            txn.drop(db, delete=False)
        pending = sorted({(max(a, b), min(a, b)) for a, b in joins})
        done = 0
        for seq in sorted(lengths):
            self.add(txn, seq, lengths[seq])
            while done < len(pending) and pending[done][0] <= seq:
                self.union(txn, *pending[done])
                done += 1
        return sum(1 for _ in self.components(txn))

    def members(self, txn: lmdb.Transaction, root: int) -> list[int]:
        """Sequence ids of the component rooted at ``root``, ascending. O(component size)."""
        out = []
        prefix = u32(root)
        cursor = txn.cursor(db=self._members)
        if cursor.set_range(prefix):
            for key in cursor.iternext(keys=True, values=False):
                if key[:4] != prefix:
                    break
                out.append(MEMBER_KEY.unpack(key)[1])
        return out

    def components(self, txn: lmdb.Transaction) -> Iterator[tuple[int, int, int]]:
        """Yield ``(root, n_sequences, n_vertices)`` of every component. O(components)."""
        for key, value in txn.cursor(db=self._comp):
            seqs, verts = COMP_VAL.unpack(value)
            yield read_u32(key), int(seqs), int(verts)

    def component_totals(self, txn: lmdb.Transaction, root: int) -> tuple[int, int]:
        raw = txn.get(u32(root), db=self._comp)
        if raw is None:
            raise MapCorruptError(f"component {root} has no totals record")
        seqs, verts = COMP_VAL.unpack(raw)
        return int(seqs), int(verts)
