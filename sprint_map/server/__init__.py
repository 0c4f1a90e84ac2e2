"""The localisation service (``sprint-map serve``): vehicles stream frames, the map answers.

See ``docs/service.md``. Modules:

```
config.py     ServerConfig: limits and settings (frozen, from_dict/to_dict)
app.py        FastAPI routes, error answers, request-size limit, request metrics
service.py    LocalisationService: sessions, frame workers, commit writer over one open map
sessions.py   Session (one drive: its Localizer, rows, decisions) and SessionRegistry (limits)
writer.py     CommitWriter: the single writer thread; commits acknowledged once durable
gate.py       MapGate: readers-writer lock between frames and a commit's critical section
payloads.py   JSON descriptor / image bytes -> one descriptor row, 4xx for bad input
metrics.py    Prometheus text format
heap.py       the start-up heap frozen out of the GC (serve), GC pauses timed
auth.py       bearer token; no token, loopback only
run.py        serve_map(): open the map, bind, run uvicorn, graceful shutdown
```
"""

from sprint_map.server.config import ServerConfig

__all__ = ["ServerConfig"]
