"""A small map to show the API with: the one-line start of the facade's examples.

networkx's examples start from a graph made in one line (``G = nx.path_graph(4)``); the
examples of :class:`~sprint_map.map.SprintMap` start from :func:`example_map`::

    from sprint_map.examples import example_map

    smap = example_map({"mon": 5, "tue": 3})  # two drives of random rows, dim 8
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from collections.abc import Mapping

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.map import SprintMap

__all__ = ["PREFIX", "example_map"]

#: The map's folder's prefix under the system's temporary directory.
PREFIX = "sprint-map-example-"


def example_map(drives: Mapping[str, int] | None = None, *, dim: int | None = None,
                seed: int = 0, config: MapConfig | None = None) -> SprintMap:
    """A writable map in a fresh temporary folder, holding one sequence per drive of
    seeded random rows. O(frames * dim).

    The drives are added in order, as :meth:`~sprint_map.map.SprintMap.add_sequence` does
    (appended as they are, not merged); drive ``i``'s rows are the ``i``-th draw
    ``rng.standard_normal((frames, dim)).astype(np.float32)`` of one
    ``rng = np.random.default_rng(seed)``, so an example that drew its rows so reads the
    same rows back with :meth:`~sprint_map.facade.reading.MapReading.descriptors`. The folder
    is removed when the interpreter exits (:mod:`atexit`; a map still open then is removed
    too): close the map when done, and keep nothing in the folder.

    Parameters
    ----------
    drives : Mapping of str to int, optional
        Each drive's name and number of frames, in the order they are added; None or empty:
        a map without sequences.
    dim : int, optional
        The rows' length; default ``config.dim``, or 8 without a ``config``.
    seed : int, default 0
        The seed of the rows: the same seed, the same rows.
    config : MapConfig, optional
        The map's configuration; default ``MapConfig(dim=dim)``.

    Returns
    -------
    SprintMap
        The map, open for writing; its folder is ``smap.path``.

    Raises
    ------
    InputError
        ``dim`` and ``config.dim`` differ.
    EmptySequenceError
        A drive of no frames (``add_sequence`` refuses it); the folder is removed at once.

    Examples
    --------
    >>> import numpy as np
    >>> from sprint_map.examples import example_map
    >>> smap = example_map({"mon": 5, "tue": 3})
    >>> [(s.name, s.length) for s in smap.sequences()], smap.config.dim
    ([('mon', 5), ('tue', 3)], 8)
    >>> rows = np.random.default_rng(0).standard_normal((5, 8)).astype(np.float32)
    >>> bool((smap.descriptors(0) == rows).all())
    True
    >>> smap.close()
    >>> from sprint_map import MapConfig
    >>> example_map(dim=16, config=MapConfig(dim=8))
    Traceback (most recent call last):
        ...
    sprint_map.errors.InputError: dim 16 is not the config's dim 8
    """
    if config is None:
        config = MapConfig(dim=8 if dim is None else dim)
    elif dim is not None and dim != config.dim:
        raise InputError(f"dim {dim} is not the config's dim {config.dim}")
    folder = tempfile.mkdtemp(prefix=PREFIX)
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    smap = SprintMap.create(folder, config)
    try:
        rng = np.random.default_rng(seed)
        for name, frames in (drives or {}).items():
            rows = rng.standard_normal((frames, config.dim)).astype(np.float32)
            smap.add_sequence(rows, name=name)
    except BaseException:
        smap.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return smap
