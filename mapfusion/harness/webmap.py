"""The interactive map of a run directory (``mapfusion plot RUN --html FILE``): a Leaflet map made
with folium, that works offline.

Leaflet itself is inlined from the ``django-js-lib-leaflet`` package (Leaflet 1.9.4's files, no
other code), so the page needs no network: our own road map is a layer, OpenStreetMap's tiles
show beneath it when the browser is online. Layers (toggled): roads, truth, odometry baseline,
Map-Fusion, GPS fixes, map priors, GPS-denied zones; hovering a pose shows its time, its errors
and whether a prior was applied; the error over distance is a picture in the corner.
"""

from __future__ import annotations

import base64
import io
from importlib import resources
from pathlib import Path

import numpy as np

from mapfusion.errors import InputError

#: The road layer's colour: what the browser test looks for in a screenshot.
ROAD_COLOUR = "#5a5a5a"
COLOURS = {"truth": "#000000", "odometry": "#1f77b4", "mapfusion": "#d62728", "gps": "#2ca02c",
           "map_prior": "#ff7f0e", "gps_denied": "#ffa500"}
#: Poses with hover details: one a second of driving at 10 Hz keeps the page light.
HOVER_EVERY = 10


def _data_url(name: str, mime: str) -> str:
    data = resources.files("js_lib_leaflet").joinpath("static", "js_lib_leaflet", name).read_bytes()
    return f"data:{mime};base64,{base64.b64encode(data).decode()}"


def _road_lines(road, lo: np.ndarray, hi: np.ndarray) -> list[list[list[float]]]:
    """The road map's edges inside the box, as lon/lat polylines (way-points of one edge in order)."""
    keep = np.all((road.xy_m >= lo) & (road.xy_m <= hi), axis=1) & ~road.is_join
    idx = np.flatnonzero(keep)
    if not len(idx):
        return []
    edge = road.edge[idx]
    lines = []
    start = 0
    for k in range(1, len(idx) + 1):
        if k == len(idx) or edge[k] != edge[start] or idx[k] != idx[k - 1] + 1:
            seg = idx[start:k]
            if len(seg) >= 2:
                lat, lon = road.projection.to_geo(road.xy_m[seg, 0], road.xy_m[seg, 1])
                lines.append([[float(a), float(b)] for a, b in zip(lat, lon)])
            start = k
    return lines


def _error_png(run: Path) -> str:
    """The error over distance (matplotlib), as a data URL."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapfusion.formats import read_tum
    from mapfusion.metrics import associate

    from .plot import _truth

    t, xy, _ = _truth(run)
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    fig, ax = plt.subplots(figsize=(4.0, 2.0), dpi=100)
    for name, key in (("estimate_odometry.tum", "odometry"), ("estimate_mapfusion.tum", "mapfusion")):
        if (run / name).exists():
            te, xe, _ = read_tum(run / name)
            ia, ib = associate(te, t)
            ax.plot(dist[ib], np.hypot(*(xe[ia, :2] - xy[ib]).T), color=COLOURS[key], lw=1, label=key)
    ax.set_xlabel("distance (m)", fontsize=7)
    ax.set_ylabel("error (m)", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.legend(fontsize=6)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _hover_points(gj: dict, run: Path) -> list[dict]:
    """Map-Fusion poses (one a second) with their time, errors and whether a prior was applied."""
    from mapfusion.formats import read_tum
    from mapfusion.metrics import associate

    from .plot import _truth

    if not (run / "estimate_mapfusion.tum").exists():
        return []
    t, xy, _ = _truth(run)
    te, xe, _ = read_tum(run / "estimate_mapfusion.tum")
    prior_t = {round(f["properties"]["t_s"], 3) for f in gj["features"] if f["properties"]["layer"] == "map_prior"}
    ia, ib = associate(te, t)
    odo_err: dict[float, float] = {}
    if (run / "estimate_odometry.tum").exists():
        to, xo, _ = read_tum(run / "estimate_odometry.tum")
        ja, jb = associate(to, t)
        odo_err = {round(float(to[a]), 3): float(np.hypot(*(xo[a, :2] - xy[b]))) for a, b in zip(ja, jb)}
    mf = next(f for f in gj["features"] if f["properties"]["layer"] == "mapfusion")["geometry"]["coordinates"]
    out = []
    for a, b in list(zip(ia, ib))[::HOVER_EVERY]:
        lon, lat = mf[a]
        odo = odo_err.get(round(float(te[a]), 3))
        out.append({"lat": lat, "lon": lon, "t_s": round(float(te[a]), 2),
                    "error_m": round(float(np.hypot(*(xe[a, :2] - xy[b]))), 2),
                    "odometry_error_m": None if odo is None else round(odo, 2),
                    "prior": round(float(te[a]), 3) in prior_t})
    return out


def write_html(run_dir: str | Path, out: str | Path, road=None) -> Path:
    """The interactive map of a run directory (see the module docstring)."""
    import folium

    from .export import run_geojson

    run = Path(run_dir)
    gj = run_geojson(run, road)  # refuses a folder that is not a run directory, before the map is read
    if road is None:
        from mapfusion.formats import read_toml
        from mapfusion.roadmap import RoadMap

        road = RoadMap.from_osm(read_toml(run / "scenario.toml", "scenario file", InputError)["map"])
    truth = next(f for f in gj["features"] if f["properties"]["layer"] == "truth")["geometry"]["coordinates"]
    lons, lats = np.array([p[0] for p in truth]), np.array([p[1] for p in truth])
    m = folium.Map(location=[float(lats.mean()), float(lons.mean())], zoom_start=15, tiles=None, control_scale=True)
    # Leaflet inlined: no CDN, so the page works offline; folium's other defaults are not needed
    m.default_js = [("leaflet", _data_url("leaflet.js", "text/javascript"))]
    m.default_css = [("leaflet_css", _data_url("leaflet.css", "text/css"))]
    folium.TileLayer("OpenStreetMap", name="OpenStreetMap (online)", show=True).add_to(m)
    x, y = road.projection.to_enu(lats, lons)
    pad = 300.0
    lo, hi = np.array([np.min(x), np.min(y)]) - pad, np.array([np.max(x), np.max(y)]) + pad
    lines = [[[round(b, 7), round(a, 7)] for a, b in line] for line in _road_lines(road, lo, hi)]
    folium.GeoJson({"type": "Feature", "properties": {}, "geometry": {"type": "MultiLineString", "coordinates": lines}},
                   name="roads (this test bed's road map)",
                   style_function=lambda _f: {"color": ROAD_COLOUR, "weight": 3, "opacity": 1.0}).add_to(m)
    for layer, label in (("truth", "truth"), ("odometry", "odometry (no map)"), ("mapfusion", "Map-Fusion")):
        group = folium.FeatureGroup(name=label, show=True)
        for f in gj["features"]:
            if f["properties"]["layer"] == layer:
                ate = f["properties"].get("ate_m")
                folium.PolyLine([[b, a] for a, b in f["geometry"]["coordinates"]], color=COLOURS[layer], weight=2,
                                tooltip=label + (f" (ATE {ate:.2f} m)" if isinstance(ate, (int, float)) else "")
                                ).add_to(group)
        group.add_to(m)
    for layer, label in (("gps", "GPS fixes"), ("map_prior", "map priors")):
        group = folium.FeatureGroup(name=label, show=layer == "map_prior")
        for f in gj["features"]:
            if f["properties"]["layer"] == layer:
                lon, lat = f["geometry"]["coordinates"]
                tip = ", ".join(f"{k} {v}" for k, v in f["properties"].items() if k != "layer")
                folium.CircleMarker([lat, lon], radius=3, color=COLOURS[layer], fill=True, tooltip=tip).add_to(group)
        group.add_to(m)
    zones = [f for f in gj["features"] if f["properties"]["layer"] == "gps_denied"]
    if zones:
        folium.GeoJson({"type": "FeatureCollection", "features": zones}, name="GPS-denied zones",
                       style_function=lambda _f: {"color": COLOURS["gps_denied"], "fillOpacity": 0.3}).add_to(m)
    hover = folium.FeatureGroup(name="poses (hover: time, error, prior)", show=True)
    for p in _hover_points(gj, run):
        folium.CircleMarker([p["lat"], p["lon"]], radius=2, color=COLOURS["mapfusion"], fill=True, opacity=0.6,
                            tooltip=f"t = {p['t_s']} s: Map-Fusion error {p['error_m']} m"
                                    + ("" if p["odometry_error_m"] is None else
                                       f", odometry (no map) error {p['odometry_error_m']} m")
                                    + (", map prior applied" if p["prior"] else "")).add_to(hover)
    hover.add_to(m)
    folium.LayerControl(collapsed=False).add_to(m)
    img = _error_png(run)
    m.get_root().html.add_child(folium.Element(
        f'<img src="{img}" alt="error over distance" style="position:absolute;bottom:20px;left:10px;z-index:1000;'
        'background:white;border:1px solid #999">'))
    m.fit_bounds([[float(lats.min()), float(lons.min())], [float(lats.max()), float(lons.max())]])
    p = Path(out)
    m.save(str(p))
    return p


def needs_network(path: str | Path) -> bool:
    """Whether a written page loads a script or a style sheet from the network."""
    text = Path(path).read_text()
    return any(s in text for s in ('src="http', "src='http", 'href="http', "href='http"))
