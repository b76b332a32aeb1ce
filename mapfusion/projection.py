"""The one projection between WGS84 lat/lon and the local ENU frame used everywhere.

A transverse Mercator projection centred on an origin (normally the map's centre). Within a
few tens of kilometres of the origin its scale error is below 1e-5, so ENU metres are metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import Transformer

from .errors import InputError


@dataclass(frozen=True)
class LocalProjection:
    """Transverse Mercator centred on (``origin_lat_deg``, ``origin_lon_deg``).

    ``to_enu`` and ``to_geo`` accept scalars or numpy arrays and return the same shape.
    """

    origin_lat_deg: float
    origin_lon_deg: float
    _fwd: Transformer = field(init=False, repr=False, compare=False)
    _inv: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        lat, lon = self.origin_lat_deg, self.origin_lon_deg
        if not (np.isfinite(lat) and np.isfinite(lon) and -85.0 < lat < 85.0 and -180.0 <= lon <= 180.0):
            raise InputError(f"projection origin out of range: lat={lat}, lon={lon}")
        proj = (
            f"+proj=tmerc +lat_0={lat:.9f} +lon_0={lon:.9f} +k=1 +x_0=0 +y_0=0 "
            "+ellps=WGS84 +units=m +no_defs"
        )
        object.__setattr__(self, "_fwd", Transformer.from_crs("EPSG:4326", proj, always_xy=True))
        object.__setattr__(self, "_inv", Transformer.from_crs(proj, "EPSG:4326", always_xy=True))

    @property
    def proj_string(self) -> str:
        """The PROJ definition of the ENU frame (for other tools, e.g. SUMO's netconvert)."""
        return (
            f"+proj=tmerc +lat_0={self.origin_lat_deg:.9f} +lon_0={self.origin_lon_deg:.9f} "
            "+k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
        )

    def to_enu(self, lat_deg, lon_deg):
        """WGS84 (lat, lon) in degrees → local (x east, y north) in metres."""
        x, y = self._fwd.transform(lon_deg, lat_deg)
        return x, y

    def to_geo(self, x_m, y_m):
        """Local (x east, y north) in metres → WGS84 (lat, lon) in degrees."""
        lon, lat = self._inv.transform(x_m, y_m)
        return lat, lon

    def __reduce__(self):
        # Transformers do not pickle across processes reliably; rebuild from the origin.
        return (LocalProjection, (self.origin_lat_deg, self.origin_lon_deg))
