"""The ``sprint-map`` command line (:mod:`sprint_map.cli.main.main`), its reference and progress bar."""

__all__: list[str] = []
