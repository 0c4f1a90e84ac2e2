"""Default names of unnamed drives never collide with a user's names (issue 14, item 2)."""

from __future__ import annotations

import httpx
import numpy as np

from sprint_map.map import SprintMap
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import run_service
from tests.helpers.worlds import drive


async def _drive(client: httpx.AsyncClient, name: str | None, rows: np.ndarray) -> httpx.Response:
    """Create a session (named or not), stream ``rows``, commit; the commit's answer."""
    created = await client.post("/v1/sessions", json={"name": name} if name else None)
    assert created.status_code == 201, created.text
    sid = created.json()["session_id"]
    for row in rows:
        answer = await client.post(f"/v1/sessions/{sid}/frames", json={"descriptor": row.tolist()})
        assert answer.status_code == 200, answer.text
    return await client.post(f"/v1/sessions/{sid}/commit")


def test_unnamed_drives_never_collide_with_named_ones(one_drive_map, places, rng):
    """Item 2: a session named ``seq-2`` commits as sequence 1; the unnamed drive that then
    becomes sequence 2 got 409 ``duplicate_name`` for its default name, retries included."""

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        named = await _drive(client, "seq-2", drive(places[:10], rng))
        assert (named.status_code, named.json()["seq_id"]) == (200, 1)
        unnamed = await _drive(client, None, drive(places[10:20], rng))
        assert unnamed.status_code == 200, unnamed.text
        assert unnamed.json()["seq_id"] == 2 and unnamed.json()["name"] == "seq-2-2"
        # A name promised to an open session is not taken by an unnamed drive's default.
        held = (await client.post("/v1/sessions", json={"name": "seq-3"})).json()["session_id"]
        other = await _drive(client, None, drive(places[20:30], rng))
        assert (other.status_code, other.json()["name"]) == (200, "seq-3-2"), other.text
        for row in drive(places[30:40], rng):
            await client.post(f"/v1/sessions/{held}/frames", json={"descriptor": row.tolist()})
        kept = await client.post(f"/v1/sessions/{held}/commit")
        assert (kept.status_code, kept.json()["name"]) == (200, "seq-3"), kept.text
        assert (await _drive(client, None, drive(places[:5], rng))).json()["name"] == "seq-5"

    run_service(one_drive_map, body)
    with SprintMap.open(one_drive_map, readonly=True) as m:
        assert [s.name for s in m.sequences()] == ["first", "seq-2", "seq-2-2", "seq-3-2",
                                                   "seq-3", "seq-5"]



def test_a_default_name_is_claimed_while_its_drive_commits():
    """A session being created while an unnamed drive commits as ``seq-5`` cannot take
    ``seq-5`` (the map may not show it yet); a failed commit gives the name back."""
    import pytest

    from sprint_map.server.errors import ApiError
    from sprint_map.server.sessions import Session, SessionRegistry
    from sprint_map.storage.sequence_writer import default_name

    registry = SessionRegistry(10, 10, 1 << 20)
    registry.add(Session("seq-5", None, 4))  # type: ignore[arg-type]
    seen = []

    class Begun:  # stands for SequenceWriter(store, None, source, taken)
        def __init__(self, taken):
            seen.append(set(taken))
            self.name = default_name(5, taken.__contains__)

    assert registry.begin_default(Begun).name == "seq-5-2"
    assert seen == [{"seq-5"}]
    with pytest.raises(ApiError) as refused:
        registry.add(Session("seq-5-2", None, 4))  # type: ignore[arg-type]
    assert (refused.value.status, refused.value.code) == (409, "duplicate_name")
    assert registry.begin_default(Begun).name == "seq-5-3"  # claimed names are taken too
    registry.release("seq-5-2")  # its commit failed
    registry.add(Session("seq-5-2", None, 4))  # type: ignore[arg-type]
