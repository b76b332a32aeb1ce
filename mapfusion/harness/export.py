"""A run directory for GIS tools: GeoJSON (RFC 7946: WGS84, longitude first, counter-clockwise
outer rings) and GPX tracks (``mapfusion export``, and ``run.geojson`` in every run directory).

Layers: the truth, the odometry baseline and Map-Fusion as LineStrings (with their ATE), the GPS
fixes and the map priors as Points (time; σ of a fix; the estimate's error at a prior), the
GPS-denied zones as Polygons (a 10 m corridor along the truth).
"""

from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from mapfusion.errors import InputError
from mapfusion.formats import read_gps_csv, read_tum
from mapfusion.metrics import associate

from .plot import _json, _spans, _truth

#: Decimal places of a coordinate: 1e-7 degrees is about a centimetre.
DIGITS = 7
#: Half-width of a GPS-denied zone's polygon around the truth, metres.
ZONE_HALF_WIDTH_M = 10.0
ESTIMATES = {"estimate_odometry.tum": ("odometry", "odometry (no map)"),
             "estimate_mapfusion.tum": ("mapfusion", "Map-Fusion")}


def _projection(run: Path, road=None):
    if road is not None:
        return road.projection
    from mapfusion.formats import read_toml
    from mapfusion.roadmap import RoadMap

    sc = run / "scenario.toml"
    if not sc.exists():
        raise InputError(f"{run}: not a run directory (no scenario.toml: its map defines the frame)")
    try:
        return RoadMap.from_osm(read_toml(sc, "scenario file", InputError)["map"]).projection
    except KeyError:
        raise InputError(f"{sc}: no map") from None


def _lonlat(proj, xy: np.ndarray) -> list[list[float]]:
    lat, lon = proj.to_geo(xy[:, 0], xy[:, 1])
    return [[round(float(a), DIGITS), round(float(b), DIGITS)] for a, b in zip(np.atleast_1d(lon), np.atleast_1d(lat))]


def _zones(proj, xy: np.ndarray, denied: np.ndarray) -> list[dict]:
    from shapely.geometry import LineString
    from shapely.geometry.polygon import orient

    out = []
    for a, b in _spans(denied):
        if b - a < 1:
            continue
        poly = orient(LineString(xy[a:b + 1]).buffer(ZONE_HALF_WIDTH_M, cap_style="flat"), sign=1.0)
        if poly.geom_type != "Polygon":
            continue
        ring = _lonlat(proj, np.asarray(poly.exterior.coords))
        ring[-1] = ring[0]  # closed exactly, after rounding
        out.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring]},
                    "properties": {"layer": "gps_denied", "name": "GPS-denied zone"}})
    return out


def run_geojson(run_dir: str | Path, road=None) -> dict:
    """The run directory as a GeoJSON FeatureCollection (see the module docstring)."""
    run = Path(run_dir)
    if not (run / "truth.csv").exists() and not (run / "truth.tum").exists():
        raise InputError(f"{run}: not a run directory (no truth.csv or truth.tum)")
    proj = _projection(run, road)
    t, xy, denied = _truth(run)
    metrics = _json(run / "metrics.json")
    feats: list[dict] = [{"type": "Feature", "geometry": {"type": "LineString", "coordinates": _lonlat(proj, xy)},
                          "properties": {"layer": "truth", "name": "truth", "t_start_s": float(t[0]),
                                         "t_end_s": float(t[-1])}}]
    prior_t = np.asarray(_json(run / "fusion_events.json").get("map_prior_t", []), float)
    for name, (key, label) in ESTIMATES.items():
        if not (run / name).exists():
            continue
        te, xe, _ = read_tum(run / name)
        if len(te) < 2:
            continue
        feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": _lonlat(proj, xe[:, :2])},
                      "properties": {"layer": key, "name": label, "ate_m": metrics.get(f"ate_{key}_m")}})
        if key == "mapfusion" and len(prior_t):
            ja, _ = associate(te, prior_t, 1e-3)
            ka, kb = associate(te, t)
            err = dict(zip(ka.tolist(), np.hypot(*(xe[ka, :2] - xy[kb]).T).tolist()))
            for j in ja:
                point = {"type": "Point", "coordinates": _lonlat(proj, xe[j:j + 1, :2])[0]}
                feats.append({"type": "Feature", "geometry": point,
                              "properties": {"layer": "map_prior", "t_s": float(te[j]),
                                             "error_m": None if j not in err else round(err[j], 3)}})
    if (run / "gps.csv").exists():
        g = read_gps_csv(run / "gps.csv")
        for i in range(len(g)):
            if np.isfinite(g.lat_deg[i]) and np.isfinite(g.lon_deg[i]):
                feats.append({"type": "Feature",
                              "geometry": {"type": "Point", "coordinates": [round(float(g.lon_deg[i]), DIGITS),
                                                                            round(float(g.lat_deg[i]), DIGITS)]},
                              "properties": {"layer": "gps", "t_s": float(g.t_s[i]), "sigma_m":
                                             None if not np.isfinite(g.sigma_m[i]) else float(g.sigma_m[i])}})
    feats += _zones(proj, xy, denied)
    return {"type": "FeatureCollection", "features": feats}


def write_geojson(run_dir: str | Path, path: str | Path, road=None) -> Path:
    p = Path(path)
    p.write_text(json.dumps(run_geojson(run_dir, road), separators=(",", ":"), allow_nan=False) + "\n")
    return p


def write_gpx(run_dir: str | Path, path: str | Path, road=None) -> Path:
    """GPX 1.1: a track each for the truth, the odometry baseline and Map-Fusion (times in a
    point's <desc>, seconds from the start: a simulated drive has no calendar time)."""
    gj = run_geojson(run_dir, road)
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             '<gpx version="1.1" creator="mapfusion" xmlns="http://www.topografix.com/GPX/1/1">']
    for f in gj["features"]:
        if f["geometry"]["type"] != "LineString":
            continue
        lines.append(f"  <trk><name>{escape(f['properties']['name'])}</name><trkseg>")
        lines += [f"    <trkpt lat={quoteattr(str(lat))} lon={quoteattr(str(lon))}/>"
                  for lon, lat in f["geometry"]["coordinates"]]
        lines.append("  </trkseg></trk>")
    lines.append("</gpx>")
    p = Path(path)
    p.write_text("\n".join(lines) + "\n")
    return p


def write_sensor_bag(run_dir: str | Path, path: str | Path, road=None) -> Path:
    """The run's odometry, GPS and IMU as a bag (``NAME.bag``: ROS 1; else a ROS 2 MCAP folder) on
    /odom, /gps/fix and /imu: what ``mapfusion fuse --bag`` reads."""
    from mapfusion.bags import BagKind, write_bag
    from mapfusion.formats import read_imu_csv, tum_to_matrices

    run = Path(run_dir)
    if not (run / "odometry.tum").exists():
        raise InputError(f"{run}: not a run directory with sensors (no odometry.tum)")
    t, xyz, q = read_tum(run / "odometry.tum")
    gps = read_gps_csv(run / "gps.csv") if (run / "gps.csv").exists() else None
    imu = read_imu_csv(run / "imu.csv") if (run / "imu.csv").exists() else None
    return write_bag(path, BagKind.for_path(path), (t, tum_to_matrices(xyz, q)), gps, imu)
