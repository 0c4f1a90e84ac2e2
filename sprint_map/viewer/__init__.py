"""The map viewer: one offline page (overview, drives' match matrices, trace playback).

``sprint-map view MAP [--trace OUT]`` serves it alone (:func:`sprint_map.viewer.run.view_map`);
``sprint-map serve`` mounts the same page at ``/`` behind its token. Server-side summaries
(:mod:`~sprint_map.viewer.overview`, :mod:`~sprint_map.viewer.matrix`,
:mod:`~sprint_map.viewer.playback`) keep what the page receives bounded at any map size; the
page's script and style ship in ``static/`` (no CDN, no third-party library). FastAPI is
imported by :mod:`~sprint_map.viewer.app` only, not by this package.
"""

__all__: list[str] = []
