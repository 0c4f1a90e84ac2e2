"""The map's retrieval index: one interface, exact flat while small, segmented when large."""

__all__: list[str] = []
