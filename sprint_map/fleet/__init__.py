"""Fleet scale on Ray: an ingest farm, retrieval shards and localiser replicas (optional).

Everything here runs only when asked for (``--ray local|auto|ADDRESS`` on ``ingest`` and
``serve``, or these modules called from Python) and needs the ``ray`` extra
(``pip install -e ".[ray]"``). Importing :mod:`sprint_map` or the CLI never imports Ray: each
module imports it inside the functions that use it.

- :mod:`sprint_map.fleet.runtime`: connect to (or start) a Ray runtime from a ``--ray`` value;
- :mod:`sprint_map.fleet.shards`: retrieval shards, actors that each own a vertex range of the
  index; a search fans out and merges the top k;
- :mod:`sprint_map.fleet.farm`: the ingest farm, descriptors and localisation as Ray tasks
  against a read-only snapshot, one writer committing in order.

The package goes through the :class:`~sprint_map.map.SprintMap` facade and public modules only.
"""

from __future__ import annotations

__all__: list[str] = []
