"""Both component caches pass the one contract
(:class:`tests.helpers.contracts.ComponentCacheContract`); the shared one also loads a
component once for filters in several threads."""

from __future__ import annotations

import threading
import time

from sprint_map.hmm.cache import ComponentCache, SharedComponentCache
from tests.helpers.contracts import ComponentCacheContract


class TestComponentCache(ComponentCacheContract):
    cache_cls = ComponentCache


class TestSharedComponentCache(ComponentCacheContract):
    cache_cls = SharedComponentCache

    def test_threads_asking_for_one_component_load_it_once(self):
        cache = SharedComponentCache(1 << 20)
        loads: list[int] = []

        def slow(cid: int):
            loads.append(cid)
            time.sleep(0.02)  # a second thread arrives while the first loads
            return self.component(cid)

        got = []
        threads = [threading.Thread(target=lambda: got.append(cache.get(7, slow)))
                   for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert loads == [7] and len({id(g) for g in got}) == 1
