"""sprint-map: a persistent, lifelong visual place-recognition map (SPRINT, Latif et al. 2020)."""

from sprint_map.config import SCHEMA_VERSION, MapConfig
from sprint_map.errors import SprintMapError
from sprint_map.hmm.config import HMMConfig

__all__ = ["SCHEMA_VERSION", "HMMConfig", "MapConfig", "SprintMapError"]
__version__ = "0.1.0"
