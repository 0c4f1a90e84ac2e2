"""Synthetic multi-traversal place-recognition data for the HMM tests (descriptors, no images).

A world of routes; each route is a chain of places with a smoothly varying appearance (unit
vectors in ``dim`` dimensions, neighbours correlated like consecutive video frames). Some places
are perceptual aliases (near copies of a place elsewhere). A traversal drives along routes at a
varying speed under a condition (a global appearance shift plus a per-place change) with noise.
The database is several traversals, stored as sequences with edges between aligned frames (as
the map's merge would create them); the query is a new traversal under a new condition that
jumps between routes and crosses stretches of places the database never saw.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import faiss
import numpy as np

from sprint_map.hmm.graph import MemoryGraphSource


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass
class World:
    """Place appearances: ``routes[r]`` is an array of place ids; ``base[place]`` its look."""

    base: np.ndarray
    routes: list[np.ndarray]
    rng: np.random.Generator
    dim: int

    @classmethod
    def make(cls, rng: np.random.Generator, n_routes: int = 4, route_len: int = 150,
             dim: int = 64, smooth: float = 0.8, alias_frac: float = 0.1,
             alias_noise: float = 0.25) -> World:
        bases: list[np.ndarray] = []
        routes: list[np.ndarray] = []
        for _ in range(n_routes):
            first = len(bases)
            cur = _unit(rng.standard_normal(dim))
            for _ in range(route_len):
                cur = _unit(smooth * cur + np.sqrt(1 - smooth**2) * _unit(rng.standard_normal(dim)))
                bases.append(cur)
            routes.append(np.arange(first, first + route_len))
        base = np.array(bases)
        # Perceptual aliasing: some places look almost exactly like another place.
        n_alias = int(alias_frac * len(base))
        victims = rng.choice(len(base), n_alias, replace=False)
        models = rng.choice(len(base), n_alias, replace=False)
        for v, m in zip(victims, models, strict=True):
            base[v] = _unit(base[m] + alias_noise * _unit(rng.standard_normal(dim)))
        return cls(base, routes, rng, dim)

    def novel_route(self, length: int, smooth: float = 0.8) -> np.ndarray:
        """Append a route of places nobody mapped; return its place ids."""
        first = len(self.base)
        cur = _unit(self.rng.standard_normal(self.dim))
        new = []
        for _ in range(length):
            cur = _unit(smooth * cur + np.sqrt(1 - smooth**2) * _unit(self.rng.standard_normal(self.dim)))
            new.append(cur)
        self.base = np.vstack([self.base, np.array(new)])
        return np.arange(first, first + length)

    def drive(self, places: np.ndarray, *, condition: np.ndarray, change: float, noise: float,
              speed: tuple[float, float] = (0.7, 1.4)) -> tuple[np.ndarray, np.ndarray]:
        """Drive along ``places`` at a varying speed; return (place id per frame, descriptors)."""
        rng = self.rng
        pos = 0.0
        frames: list[int] = []
        v = rng.uniform(*speed)
        while pos <= len(places) - 1:
            frames.append(int(places[int(round(pos))]))
            v = float(np.clip(v + rng.normal(0, 0.1), *speed))
            pos += v
        place = np.array(frames)
        per_place = rng.standard_normal((len(place), self.dim))
        desc = self.base[place] + change * condition + noise * per_place / np.sqrt(self.dim)
        return place, _unit(desc).astype(np.float32)


@dataclass
class Scenario:
    """A database (map) and a query traversal with ground truth."""

    source: MemoryGraphSource
    db_place: np.ndarray            # place id of every database vertex
    db_desc: np.ndarray
    query_place: np.ndarray         # place id of every query frame
    query_desc: np.ndarray
    novel: np.ndarray               # bool per query frame: place never mapped
    seq_lengths: list[int] = field(default_factory=list)

    def knn(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        index = faiss.IndexFlatL2(self.db_desc.shape[1])
        index.add(self.db_desc)
        dists, ids = index.search(self.query_desc, k)
        return ids.astype(np.int64), dists

    def correct(self, frame: int, vertex: int, tol: int = 1) -> bool:
        """Whether ``vertex`` shows the query frame's place (within ``tol`` places on its route)."""
        return bool(abs(int(self.db_place[vertex]) - int(self.query_place[frame])) <= tol
                    and self._same_route(int(self.db_place[vertex]), int(self.query_place[frame])))

    def _same_route(self, a: int, b: int) -> bool:
        return a // self.route_len == b // self.route_len

    route_len: int = 150


def make_scenario(seed: int, *, n_routes: int = 4, route_len: int = 150, n_db: int = 3,
                  noise: float = 0.9, change: float = 0.35, edge_every: int = 2,
                  novel_len: int = 40, both_ways: bool = True) -> Scenario:
    """Build a map of ``n_db`` traversals of every route and a query that mixes known routes,
    jumps between them and a novel stretch.

    Query layout: the second half of route 0, route 1 from its start (a turn), a novel stretch
    of ``novel_len`` places, then the first two thirds of route 2.
    """
    rng = np.random.default_rng(seed)
    world = World.make(rng, n_routes=n_routes, route_len=route_len)
    dim = world.dim
    seq_lengths: list[int] = []
    db_place: list[np.ndarray] = []
    db_desc: list[np.ndarray] = []
    edges: list[tuple[int, int, float]] = []
    first_of: dict[tuple[int, int], int] = {}
    for t in range(n_db):
        condition = _unit(rng.standard_normal(dim))
        for r, route in enumerate(world.routes):
            place, desc = world.drive(route, condition=condition, change=change, noise=noise)
            first = sum(seq_lengths)
            first_of[(t, r)] = first
            seq_lengths.append(len(place))
            db_place.append(place)
            db_desc.append(desc)
            # Edges to the previous traversal of this route at aligned frames (every few frames),
            # as a merge with confident decisions would create them.
            if t > 0:
                prev_first = first_of[(t - 1, r)]
                prev_place = db_place[-1 - n_routes]
                for i in range(0, len(place), edge_every):
                    j = int(np.argmin(np.abs(prev_place - place[i])))
                    if prev_place[j] == place[i]:
                        edges.append((first + i, prev_first + j, 0.9))
                        if both_ways:
                            edges.append((prev_first + j, first + i, 0.9))
    novel_places = world.novel_route(novel_len)
    condition = _unit(rng.standard_normal(dim))
    parts = [world.routes[0][route_len // 2:], world.routes[1], novel_places,
             world.routes[2][: 2 * route_len // 3]]
    q_place: list[np.ndarray] = []
    q_desc: list[np.ndarray] = []
    for part in parts:
        place, desc = world.drive(part, condition=condition, change=change, noise=noise)
        q_place.append(place)
        q_desc.append(desc)
    query_place = np.concatenate(q_place)
    scenario = Scenario(
        source=MemoryGraphSource(seq_lengths, edges),
        db_place=np.concatenate(db_place), db_desc=np.vstack(db_desc),
        query_place=query_place, query_desc=np.vstack(q_desc),
        novel=query_place >= n_routes * route_len, seq_lengths=seq_lengths, route_len=route_len)
    return scenario
