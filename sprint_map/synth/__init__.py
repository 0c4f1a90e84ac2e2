"""Synthetic multi-traversal city data sets for testing and evaluating place recognition.

A procedurally textured grid city (perceptual aliasing by shared facade styles) is driven along
overlapping routes under different conditions (light, weather, traffic), with variable speed and
stops, and rendered by ray casting. See :func:`generate_city` (on-disk data set),
:func:`render_city` (in memory), :func:`iter_city` (streamed, one traversal at a time) and
:data:`PRESETS` (the demo's worlds, ``city`` and ``city-novel``).
"""

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
