"""The facade's parts: what :class:`~sprint_map.map.SprintMap` is made of.

``reading`` (on ``positions`` and ``search``), ``localizing``, ``upkeep`` and ``writing`` are
the mixins of the user's API; ``service`` (on ``supply``) is :attr:`SprintMap.service`, the API
of the service and the fleet; ``core`` holds what every part reads (the store, the config).
Import them through :mod:`sprint_map` (``SprintMap``, ``MapService``), not from here.
"""

__all__: list[str] = []  # its parts are reached through sprint_map (SprintMap, MapService)
