"""Synthetic multi-traversal city data sets for testing and evaluating place recognition.

A procedurally textured grid city (perceptual aliasing by shared facade styles) is driven along
overlapping routes under different conditions (light, weather, traffic), with variable speed and
stops, and rendered by ray casting. See :func:`generate_city` (on-disk data set) and
:func:`render_city` (in memory), and ``docs/frontend.md``.
"""

from sprint_map.synth.city import (
    CityConfig,
    SyntheticCity,
    SyntheticTraversal,
    generate_city,
    render_city,
)
from sprint_map.synth.conditions import CONDITIONS, Condition

__all__ = [
    "CONDITIONS",
    "CityConfig",
    "Condition",
    "SyntheticCity",
    "SyntheticTraversal",
    "generate_city",
    "render_city",
]
