"""The in-memory union-find (disjoint sets) of the package: union by size, path halving.

Used wherever a partition is computed in memory: the HMM's components of a
:class:`~sprint_map.hmm.graph.MemoryGraphSource`, the groups a removal or a summary leaves,
the synthetic city's connectivity. The map's own components are persisted in LMDB by
:class:`~sprint_map.storage.components.ComponentStore`, which must survive a crash between two
unions; this one lives for one computation.

Examples
--------
>>> sets = UnionFind(5)
>>> sets.union(0, 3); sets.union(3, 4)
>>> sets.find(4) == sets.find(0), sets.find(1) == sets.find(0)
(True, False)
>>> sets.groups()
[[0, 3, 4], [1], [2]]

Notes
-----
``find`` and ``union`` are O(alpha(n)) amortised; ``groups`` is O(n alpha(n)).
"""

from __future__ import annotations

__all__ = ["UnionFind"]


class UnionFind:
    """Disjoint sets over the items ``0 .. n - 1``, each first alone."""

    __slots__ = ("parent", "size")

    def __init__(self, n: int) -> None:
        self.parent = list(range(n))
        self.size = [1] * n

    def find(self, a: int) -> int:
        """The representative of ``a``'s set (which one is not part of the contract)."""
        parent = self.parent
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    def union(self, a: int, b: int) -> None:
        """Join the sets of ``a`` and ``b`` (nothing if they are one)."""
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return
        if self.size[ra] < self.size[rb] or (self.size[ra] == self.size[rb] and rb < ra):
            ra, rb = rb, ra
        self.parent[rb] = ra
        self.size[ra] += self.size[rb]

    def groups(self) -> list[list[int]]:
        """The sets, each ascending, in the order of their smallest items."""
        out: dict[int, list[int]] = {}
        for i in range(len(self.parent)):
            out.setdefault(self.find(i), []).append(i)
        return list(out.values())
