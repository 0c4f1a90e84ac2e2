"""A join through the service's writer (``POST /v1/joins``): sessions keep streaming and
committing beside it, and live filters follow the components the join merged."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import DIM, run_service
from tests.helpers.worlds import drive
from tests.server.test_service import frames


def test_a_join_through_the_writer_reaches_live_sessions(tmp_path: Path,
                                                         rng: np.random.Generator) -> None:
    here, there = rng.standard_normal((80, DIM)), rng.standard_normal((40, DIM))
    path, source = tmp_path / "m.map", tmp_path / "van.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.ingest(drive(here, rng), name="here")
        m.ingest(drive(there, rng), name="there", merge=False)  # its own component
    with SprintMap.create(source, MapConfig(dim=DIM)) as m:
        m.ingest(np.concatenate([drive(here[:40], rng), drive(there, rng)]), name="joiner")
    watcher_rows = drive(here, rng)
    other_rows = drive(there, rng)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        watcher = (await client.post("/v1/sessions")).json()["session_id"]
        await frames(client, watcher, watcher_rows[:20])
        other = (await client.post("/v1/sessions", json={"name": "other"})).json()["session_id"]
        await frames(client, other, other_rows[:20])
        bad = await client.post("/v1/joins", json={"source": str(path)})
        assert bad.status_code == 422 and bad.json()["error"] == "bad_input"  # itself
        unconnected = await client.post("/v1/joins", json={"source": str(source),
                                                           "merge": False,
                                                           "require_connected": True})
        assert unconnected.status_code == 409, unconnected.text
        joined = await client.post("/v1/joins", json={"source": str(source)})
        assert joined.status_code == 200, joined.text
        (report,) = joined.json()["drives"]
        assert report["name"] == "joiner" and report["connected"] and report["cross_edges"]
        comps = {c.component for c in service.map.components()}
        assert len(comps) == 1  # the joined drive links here and there
        after = await frames(client, watcher, watcher_rows[20:])
        live = service.registry.get(watcher).localizer.filter
        assert set(live.active_component_ids) <= comps
        assert sum(a["seq_id"] is not None for a in after) >= 0.8 * len(after)
        await frames(client, other, other_rows[20:])
        done = await client.post(f"/v1/sessions/{other}/commit")
        assert done.status_code == 200, done.text
        again = (await client.post("/v1/joins", json={"source": str(source)})).json()
        assert again["imported"] == 0 and again["already_present"] == 1

    run_service(path, body)
    with SprintMap.open(path, readonly=True) as m:
        assert m.check().ok
        assert [s.name for s in m.sequences()] == ["here", "there", "joiner", "other"]
