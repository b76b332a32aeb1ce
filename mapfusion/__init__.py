"""Map-Fusion: vehicle localisation fusing GPS, drifting odometry and an OpenStreetMap road map.

The engine package: road map, matcher, factor graph, metrics, file formats and the CLI. It never
imports SUMO or :mod:`sim`, so it runs on real recordings where no simulator is installed.
"""

from __future__ import annotations

import logging

from .errors import ConfigError, InputError, MapContentError, MapFileError, MapFusionError
from .projection import LocalProjection
from .roadmap import MapStats, RoadMap, RoadMapConfig, WayInfo

logging.getLogger(__name__).addHandler(logging.NullHandler())

__version__ = "0.1.0"

__all__ = [
    "RoadMap",
    "RoadMapConfig",
    "WayInfo",
    "MapStats",
    "LocalProjection",
    "MapFusionError",
    "InputError",
    "MapFileError",
    "MapContentError",
    "ConfigError",
]
