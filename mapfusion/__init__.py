"""Map-Fusion: vehicle localisation fusing GPS, drifting odometry and an OpenStreetMap road map.

The engine library: road map, matcher, the factor-graph engine and its parts, metrics and file
formats. It never imports SUMO, :mod:`sim` or its own :mod:`mapfusion.harness` (the CLI and the
pipelines above it), so it runs on real recordings where no simulator is installed.

``MapFusion`` and ``FusionConfig`` load on first use, so that importing the package (and the
CLI's ``--help``) does not pay for GTSAM.
"""

from __future__ import annotations

import logging

from .errors import ConfigError, InputError, MapContentError, MapFileError, MapFusionError
from .projection import LocalProjection
from .roadmap import MapStats, RoadMap, RoadMapConfig, WayInfo

logging.getLogger(__name__).addHandler(logging.NullHandler())

__version__ = "0.1.0"

_LAZY = {"MapFusion": ".engine", "FusionConfig": ".config"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "MapFusion",
    "FusionConfig",
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
