"""Localising a drive against a map: the streaming filter over the map's graph, and its traces."""

__all__: list[str] = []
