"""MapCore: what every part of :class:`~sprint_map.map.SprintMap` reads of its map: the open
store, the configuration the map stores, its directory and state, its warnings, and its
service API (:class:`~sprint_map.facade.service.MapService`, one per map).

The base of the facade's mixins (:mod:`sprint_map.facade`); nothing here reads LMDB past the
config record decoded once at open. O(fields) to make.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from sprint_map.config import MapConfig
from sprint_map.facade.service import MapService
from sprint_map.storage.store import MapStore
from sprint_map.storage.store_config import decode_stored_config

if TYPE_CHECKING:
    from sprint_map.facade.service import ServedMap

__all__ = ["MapCore", "stored_config"]


def stored_config(record: dict[str, Any]) -> MapConfig:
    """The configuration a map stores (its meta record, decoded JSON), or MapCorruptError if
    it is not a valid config (:func:`~sprint_map.storage.store_config.decode_stored_config`).
    The store checks its own fields of it when it opens
    (:func:`sprint_map.storage.store.decode_config`); this checks the rest. A record without
    ``centring`` is a map made before centring: its rows are stored as given, so it reads as
    ``centring={"mode": "none"}``. O(fields).
    """
    if isinstance(record, dict) and "centring" not in record:
        record = {**record, "centring": {"mode": "none"}}
    return decode_stored_config(MapConfig.from_dict, record)


class MapCore:
    """The facade's state over ``store`` (see the module docstring).

    Parameters
    ----------
    store : MapStore
        The open store.
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store
        self._config = stored_config(store.config_record)
        # every facade made of these parts is a ServedMap (SprintMap composes them all)
        self._service = MapService(cast("ServedMap", self))

    @property
    def path(self) -> Path:
        """The map's directory."""
        return self.store.path

    @property
    def config(self) -> MapConfig:
        """The map's configuration, as stored."""
        return self._config

    @property
    def readonly(self) -> bool:
        """Whether the map was opened for reading only."""
        return self.store.readonly

    @property
    def closed(self) -> bool:
        """Whether :meth:`~sprint_map.map.SprintMap.close` was called (nothing can be read
        any more)."""
        return self.store.env is None

    @property
    def service(self) -> MapService:
        """The map's service API: the plumbing that ``server`` and ``fleet`` drive the map
        with (:class:`~sprint_map.facade.service.MapService`), one per map.

        Examples
        --------
        >>> from sprint_map import MapService
        >>> from sprint_map.examples import example_map
        >>> with example_map(dim=16) as m:
        ...     print(isinstance(m.service, MapService), m.service is m.service)
        True True
        """
        return self._service

    @property
    def warnings(self) -> list[str]:
        """Problems that failed no call and lost nothing (e.g. the index cache not saved)."""
        return self.store.warnings
