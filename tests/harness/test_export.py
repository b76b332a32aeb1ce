"""GeoJSON and GPX out (issue 20): RFC 7946's rules, checked on a simulated run with a GPS-denied zone."""

from __future__ import annotations

import csv
import json
import xml.etree.ElementTree as ET

import pytest

from mapfusion.harness.cli import main

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    sc = d / "s.toml"
    sc.write_text('name = "exp"\nmap = "grid"\nseed = 2\nduration_s = 150.0\nmin_route_m = 1000.0\n'
                  '[gps]\nmode = "continuous"\n[[tunnels]]\nstart_m = 700.0\nend_m = 800.0\n')
    assert main(["run", str(sc), "--out", str(d / "out"), "--no-plot"]) == 0
    return d / "out" / "exp"


def _positions(geom: dict) -> list:
    c = geom["coordinates"]
    if geom["type"] == "Point":
        return [c]
    return c if geom["type"] == "LineString" else [p for ring in c for p in ring]


def _signed_area(ring: list) -> float:
    return 0.5 * sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(ring, ring[1:]))


def test_run_geojson_follows_rfc_7946(run):
    text = (run / "run.geojson").read_text()
    gj = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert gj["type"] == "FeatureCollection" and "crs" not in gj  # RFC 7946 §4: WGS84 only, no crs member
    layers = {f["properties"]["layer"] for f in gj["features"]}
    assert {"truth", "odometry", "mapfusion", "gps", "gps_denied"} <= layers
    for f in gj["features"]:
        assert f["type"] == "Feature" and isinstance(f["properties"], dict)
        g = f["geometry"]
        for pos in _positions(g):
            assert len(pos) == 2 and -180 <= pos[0] <= 180 and -90 <= pos[1] <= 90
        if g["type"] == "LineString":
            assert len(g["coordinates"]) >= 2
        if g["type"] == "Polygon":
            for i, ring in enumerate(g["coordinates"]):
                assert len(ring) >= 4 and ring[0] == ring[-1]  # §3.1.6: closed linear rings
                # §3.1.6: the exterior ring counter-clockwise (positive area with x = lon, y = lat)
                assert (_signed_area(ring) > 0) == (i == 0)
    # §3.1.1: longitude first — the truth starts where truth.csv's first row is
    with open(run / "truth.csv", newline="") as fh:
        first = next(csv.DictReader(fh))
    truth = next(f for f in gj["features"] if f["properties"]["layer"] == "truth")
    lon, lat = truth["geometry"]["coordinates"][0]
    assert abs(lon - float(first["lon"])) < 1e-6 and abs(lat - float(first["lat"])) < 1e-6


def test_export_writes_geojson_and_gpx(run, tmp_path):
    assert main(["export", str(run), "--geojson", str(tmp_path / "r.geojson"), "--gpx", str(tmp_path / "r.gpx")]) == 0
    gj = json.loads((tmp_path / "r.geojson").read_text())
    lines = {f["properties"]["name"]: f["geometry"]["coordinates"] for f in gj["features"]
             if f["geometry"]["type"] == "LineString"}
    ns = {"g": "http://www.topografix.com/GPX/1/1"}
    root = ET.parse(tmp_path / "r.gpx").getroot()
    tracks = {t.find("g:name", ns).text: t.findall(".//g:trkpt", ns) for t in root.findall("g:trk", ns)}
    assert set(tracks) == set(lines) == {"truth", "odometry (no map)", "Map-Fusion"}
    for name, pts in tracks.items():
        assert len(pts) == len(lines[name])
        assert [float(pts[0].get("lon")), float(pts[0].get("lat"))] == lines[name][0]


def test_export_bad_input(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--geojson", str(tmp_path / "x.geojson")]) == 2
    assert main(["export", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "not a run directory" in err[0] and "--geojson" in err[1]


def test_the_html_map_is_self_contained(run, tmp_path):
    from mapfusion.harness.webmap import needs_network

    page = tmp_path / "map.html"
    assert main(["plot", str(run), "--html", str(page)]) == 0
    text = page.read_text()
    assert not needs_network(page)  # Leaflet inlined: the page works offline
    assert "roads (this test bed" in text and "Map-Fusion" in text and "map prior" in text
    assert "Map-Fusion error" in text and "odometry (no map) error" in text  # hover details per pose


CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser") if __import__("os").path.exists(p)), None)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_the_html_map_draws_its_roads_in_a_real_browser(run, tmp_path):
    """Headless Chromium, no network: the road layer (our own map) is drawn."""
    import subprocess

    import matplotlib.image as mpimg
    import numpy as np

    from mapfusion.harness.webmap import ROAD_COLOUR

    page, shot = tmp_path / "map.html", tmp_path / "shot.png"
    assert main(["plot", str(run), "--html", str(page)]) == 0
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync",
                    f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1000,800", "--virtual-time-budget=5000",
                    f"--screenshot={shot}", page.as_uri()], capture_output=True, timeout=120, check=True)
    img = (mpimg.imread(shot)[:, :, :3] * 255).round().astype(int)
    road = np.array([int(ROAD_COLOUR[i:i + 2], 16) for i in (1, 3, 5)])
    road_pixels = int(np.all(np.abs(img - road) <= 2, axis=2).sum())
    assert road_pixels > 2000, road_pixels  # the grid's streets, three pixels wide
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # a drawn map, not a blank page
