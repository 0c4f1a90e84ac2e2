"""The HMM's view of a persistent map: components as compact arrays, loaded on demand.

:class:`MapGraphSource` implements the :class:`sprint_map.hmm.graph.GraphSource` protocol over
LMDB, so the HMM (which knows nothing of storage) can ask for the component of a retrieved
vertex and for a component's sequences and edges. Nothing else of the map is touched.
"""

from __future__ import annotations

import numpy as np

from sprint_map.hmm.graph import ComponentGraph
from sprint_map.storage.keys import read_u32, u64
from sprint_map.storage.store import MapStore


class MapGraphSource:
    """GraphSource over a :class:`MapStore`.

    Notes
    -----
    ``components_of`` costs one LMDB cursor seek per vertex and one union-find walk and one
    sequence read per distinct sequence: O(k log n_sequences) per frame for k hits. Removed
    sequences are invisible: their records, edges and component memberships are gone, and the
    store's search never returns their vertices. ``load_component`` costs
    O(S log n + E_c) for a component of S sequences and E_c edges.
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store

    def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Component id (union-find root sequence) of each global vertex id."""
        store = self.store
        out = np.empty(len(vertex_ids), dtype=np.int64)
        with store.env.read() as txn:
            cursor = txn.cursor(db=store.env.db("vrange"))
            roots: dict[int, tuple[int, int]] = {}  # seq -> (root, first vertex)
            for i, vid in enumerate(np.asarray(vertex_ids, dtype=np.int64).tolist()):
                if vid < 0 or not cursor.set_range(u64(vid)):
                    raise ValueError(f"vertex {vid} is not in the map")
                seq = read_u32(cursor.value())
                known = roots.get(seq)
                if known is None:
                    known = roots[seq] = (store.uf.find(txn, seq),
                                          store.sequence(seq, txn).first_vertex)
                if vid < known[1]:  # the floor seek passed a removed range: never a hit
                    raise ValueError(f"vertex {vid} belonged to a removed sequence")
                out[i] = known[0]
        return out

    def load_component(self, component_id: int) -> ComponentGraph:
        """The sequences and inter-sequence edges of one component, as compact arrays."""
        store = self.store
        with store.env.read() as txn:
            seqs = store.component_sequences(component_id, txn)
            src: list[int] = []
            dst: list[int] = []
            weight: list[float] = []
            for seq in seqs:
                for edge in store.edges_from(seq.first_vertex, seq.last_vertex, txn):
                    src.append(edge.src)
                    dst.append(edge.dst)
                    weight.append(edge.weight)
        return ComponentGraph(
            component_id=component_id,
            seq_ids=np.array([s.seq_id for s in seqs], dtype=np.int64),
            seq_first=np.array([s.first_vertex for s in seqs], dtype=np.int64),
            seq_len=np.array([s.length for s in seqs], dtype=np.int64),
            edge_src=np.array(src, dtype=np.int64),
            edge_dst=np.array(dst, dtype=np.int64),
            edge_weight=np.array(weight, dtype=np.float64),
        )
