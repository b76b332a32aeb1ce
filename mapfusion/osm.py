"""Reading drivable roads from OSM files (.osm, .osm.gz, .osm.bz2, .osm.pbf) with osmium."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import osmium

from .errors import MapContentError, MapFileError

log = logging.getLogger(__name__)

#: Highway classes a passenger car may drive on. Footways, cycleways, paths, steps, tracks,
#: bus guideways, raceways and ways under construction or only proposed are left out.
DRIVABLE_HIGHWAYS: tuple[str, ...] = (
    "motorway",
    "motorway_link",
    "trunk",
    "trunk_link",
    "primary",
    "primary_link",
    "secondary",
    "secondary_link",
    "tertiary",
    "tertiary_link",
    "unclassified",
    "residential",
    "living_street",
    "service",
    "road",
)

OSM_SUFFIXES: tuple[str, ...] = (".osm", ".osm.gz", ".osm.bz2", ".osm.pbf", ".pbf", ".xml")

#: ``tunnel=*`` values that put a road under ground or a building (GPS-denied).
TUNNEL_VALUES = frozenset({"yes", "building_passage", "covered"})
BRIDGE_VALUES_NO = frozenset({"no", "false", "0"})


@dataclass(frozen=True)
class OsmWay:
    """One drivable OSM way, with its nodes' ids and coordinates in order."""

    way_id: int
    node_ids: np.ndarray  # (n,) int64
    lat_deg: np.ndarray  # (n,)
    lon_deg: np.ndarray  # (n,)
    highway: str
    name: str
    lanes: int | None
    oneway: bool
    tunnel: bool
    bridge: bool
    layer: int
    roundabout: bool
    travel: int = 0  # +1: only in the drawing direction, -1: only against it, 0: both (travel_direction)


def parse_lanes(value: str | None) -> int | None:
    """The first whole number in an OSM ``lanes`` value ("2", "2;3", " 4 "), else None."""
    if not value:
        return None
    head = value.replace(",", ";").split(";")[0].strip()
    try:
        n = int(float(head))
    except ValueError:
        return None
    return n if 1 <= n <= 20 else None


def parse_layer(value: str | None) -> int:
    """OSM ``layer`` as an int (missing or malformed → 0)."""
    if not value:
        return 0
    try:
        return int(float(value.split(";")[0]))
    except ValueError:
        return 0


def _is_oneway(tags, highway: str, roundabout: bool) -> bool:
    v = tags.get("oneway", "")
    if v in ("yes", "true", "1", "-1", "reversible"):
        return True
    if v in ("no", "false", "0"):
        return False
    # implied oneway (OSM wiki): motorways and roundabouts
    return highway in ("motorway", "motorway_link") or roundabout


def travel_direction(tags, highway: str, roundabout: bool) -> int:
    """Which way a vehicle may drive a way: +1 only in its drawing direction, -1 only against it
    (``oneway=-1``), 0 both ways (a two-way road, or ``oneway=reversible``, whose direction changes
    with the time of day)."""
    v = tags.get("oneway", "")
    if v == "-1":
        return -1
    if v == "reversible":
        return 0
    return 1 if _is_oneway(tags, highway, roundabout) else 0


class _WayCollector(osmium.SimpleHandler):
    def __init__(self, drivable: frozenset[str]) -> None:
        super().__init__()
        self.drivable = drivable
        self.ways: list[OsmWay] = []
        self.skipped_invalid = 0
        self.any_object = False

    def way(self, w) -> None:
        self.any_object = True
        tags = w.tags
        highway = tags.get("highway")
        if highway not in self.drivable or tags.get("area") == "yes":
            return
        ids, lats, lons = [], [], []
        for nd in w.nodes:
            loc = nd.location
            if not loc.valid():
                # a node the extract does not hold: cut the way there (extract borders)
                self.skipped_invalid += 1
                continue
            ids.append(nd.ref)
            lats.append(loc.lat)
            lons.append(loc.lon)
        if len(ids) < 2:
            return
        roundabout = tags.get("junction") in ("roundabout", "circular")
        self.ways.append(
            OsmWay(
                way_id=int(w.id),
                node_ids=np.asarray(ids, dtype=np.int64),
                lat_deg=np.asarray(lats, dtype=float),
                lon_deg=np.asarray(lons, dtype=float),
                highway=highway,
                name=tags.get("name", ""),
                lanes=parse_lanes(tags.get("lanes")),
                oneway=_is_oneway(tags, highway, roundabout),
                tunnel=tags.get("tunnel", "no") in TUNNEL_VALUES or tags.get("covered") == "yes",
                bridge=tags.get("bridge", "no") not in BRIDGE_VALUES_NO,
                layer=parse_layer(tags.get("layer")),
                roundabout=roundabout,
                travel=travel_direction(tags, highway, roundabout),
            )
        )


def check_osm_path(path: str | Path) -> Path:
    """Resolve an OSM path, raising :class:`MapFileError` if it is missing or not a file."""
    p = Path(path)
    if not p.exists():
        raise MapFileError(f"{p}: no such file")
    if not p.is_file():
        raise MapFileError(f"{p}: not a file")
    return p


def read_drivable_ways(path: str | Path, drivable: tuple[str, ...] = DRIVABLE_HIGHWAYS) -> list[OsmWay]:
    """All drivable ways of an OSM file, in file order.

    Raises :class:`MapFileError` for a missing, unreadable, truncated or non-OSM file and
    :class:`MapContentError` when the file holds no drivable road.
    """
    p = check_osm_path(path)
    collector = _WayCollector(frozenset(drivable))
    error = None
    try:
        collector.apply_file(str(p), locations=True)
    except RuntimeError as exc:
        error = str(exc).strip()
    # raised outside the handler: osmium's traceback (which holds its reader thread pool) is freed here,
    # so no live pool outlives the call in an exception a caller keeps, to be destroyed in a forked child
    if error is not None:
        raise MapFileError(f"{p}: not a readable OSM file ({error})")
    if not collector.any_object:
        raise MapContentError(f"{p}: holds no OSM ways at all")
    if not collector.ways:
        raise MapContentError(f"{p}: no drivable road (highway={'/'.join(drivable[:4])}/...) in the file")
    if collector.skipped_invalid:
        log.info("%s: %d way nodes outside the extract were skipped", p, collector.skipped_invalid)
    return collector.ways
