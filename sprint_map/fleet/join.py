"""A join's imported drives localised in parallel as Ray tasks (``sprint-map join --ray``).

Every imported drive of a join is localised against the same map, the target as it was before
the join (:mod:`sprint_map.merge.join`), so the drives are independent: each is a Ray task that
opens the target and the source read-only (a shared filesystem, as for the ingest farm:
``docs/fleet.md``) and returns the drive's cross-map edges (:meth:`MapService.localise_for_join
<sprint_map.facade.service.MapService.localise_for_join>`). The writer commits them all in the
join's one transaction. The result equals the serial join's: the same drives, localised by the
same code against the same snapshot (the target does not change until the join commits).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sprint_map import DriveLocalisation, HMMConfig, LocaliseMany
from sprint_map.errors import SprintMapError
from sprint_map.map import SprintMap

__all__ = ["TASK_RETRIES", "farm_localise_join", "localise_joined_drive"]

#: Ray retries of a drive's task whose worker died (the task is pure: safe to rerun).
TASK_RETRIES = 3


def localise_joined_drive(target: str, source: str, seq_id: int, hmm: HMMConfig | None
                          ) -> DriveLocalisation:
    """Localise drive ``seq_id`` of map ``source`` against map ``target`` (a Ray task)."""
    with SprintMap.open(target, readonly=True) as smap:
        return smap.service.localise_for_join(source, [seq_id], hmm)[0]


def farm_localise_join(target: str, source: str, hmm: HMMConfig | None = None,
                       task_options: dict[str, Any] | None = None) -> LocaliseMany:
    """A ``localise_many`` for :meth:`SprintMap.join` that runs one Ray task per drive on the
    runtime this process is connected to (:func:`sprint_map.fleet.runtime.connect`); results
    in the drives' order. A library error of a task (a bad source) is raised as itself."""
    from sprint_map.fleet.runtime import require_ray

    def run(records: Sequence[Any]) -> list[DriveLocalisation]:
        ray = require_ray()
        task = ray.remote(localise_joined_drive).options(
            max_retries=TASK_RETRIES, retry_exceptions=False, **(task_options or {}))
        refs = [task.remote(target, source, r.seq_id, hmm) for r in records]
        try:
            return list(ray.get(refs))
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, SprintMapError):
                raise cause from None
            raise

    return run
