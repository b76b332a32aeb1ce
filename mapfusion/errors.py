"""Exceptions of the mapfusion package: one base class, specific subclasses.

The CLI turns any :class:`InputError` into one line on stderr and exit code 2.
"""

from __future__ import annotations


class MapFusionError(Exception):
    """Base class of every error raised on purpose by :mod:`mapfusion`."""


class InputError(MapFusionError, ValueError):
    """The caller's input (a file, an argument, a configuration) is unusable."""


class MapFileError(InputError):
    """An OSM map file is missing, unreadable, truncated or not OSM at all."""


class MapContentError(InputError):
    """An OSM map file was read but holds nothing the road map can use."""


class ConfigError(InputError):
    """A configuration value or file is invalid (unknown key, wrong type, out of range)."""


class MapMismatchError(InputError):
    """Positions (GPS fixes, a recorded truth) do not lie on the map given with them: GPS of
    another place, latitude and longitude swapped, the map of another city, or another frame."""


class EngineError(InputError):
    """A measurement the engine cannot take (wrong shape, time going backwards, a call out of order)."""
