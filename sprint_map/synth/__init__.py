"""Synthetic multi-traversal data sets for testing and evaluating place recognition.

Two families that share no code path. The **city** (:mod:`.city`): a procedurally textured grid
city (perceptual aliasing by shared facade styles and lookalike streets) is driven along
overlapping routes under different conditions (light, weather, traffic), with variable speed and
stops, and rendered by ray casting. See :func:`generate_city` (on-disk data set),
:func:`render_city` (in memory), :func:`iter_city` (streamed, one traversal at a time) and
:data:`PRESETS` (the demo's worlds, ``city`` and ``city-novel``). The **latent** worlds
(:mod:`.latent`, numpy only): descriptor-level drives over latent places, imported without
OpenCV.

The city's names are imported on first use (they need OpenCV), so ``sprint_map.synth.latent``
works where OpenCV is not installed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sprint_map.util.lazy import lazy_names

if TYPE_CHECKING:
    from sprint_map.synth.city import (
        PRESETS,
        CityConfig,
        SyntheticCity,
        SyntheticTraversal,
        generate_city,
        iter_city,
        render_city,
    )
    from sprint_map.synth.conditions import CONDITIONS, Condition

__all__ = [
    "CONDITIONS",
    "PRESETS",
    "CityConfig",
    "Condition",
    "SyntheticCity",
    "SyntheticTraversal",
    "generate_city",
    "iter_city",
    "render_city",
]

_HOME = {name: "sprint_map.synth.city" for name in __all__}
_HOME.update(CONDITIONS="sprint_map.synth.conditions", Condition="sprint_map.synth.conditions")


#: The city's public names, imported on first use. O(1) after the first import.
__getattr__, __dir__ = lazy_names(__name__, _HOME)
