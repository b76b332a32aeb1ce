"""Peak memory of ``mapfusion fuse`` over a 2-hour drive against a 10-minute one (issue 19): the
engine streams its estimates, so the ratio should stay within 1.10. Each fusion runs in its own
process; its peak RSS is the child's ru_maxrss. Run: python benchmarks/bench_fuse_memory.py"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from mapfusion.formats import write_gps_csv, write_tum, yaw_to_quaternion
from mapfusion.roadmap import RoadMap
from mapfusion.synthetic import OsmBuilder

RADIUS_M, SPEED_MPS, RATE_HZ = 300.0, 10.0, 10.0


def write_drive(d: Path, name: str, duration_s: float) -> tuple[Path, Path]:
    """Laps of a 300 m circle at 10 m/s: odometry with a random-walk drift, GPS for the first 120 s."""
    n = int(duration_s * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    a = SPEED_MPS / RADIUS_M * t - math.pi / 2
    x, y = RADIUS_M * np.cos(a), RADIUS_M * np.sin(a)
    yaw = a + math.pi / 2
    drift = np.cumsum(np.random.default_rng(1).normal(0.0, 0.002, (n, 2)), axis=0)
    odo = d / f"{name}.tum"
    write_tum(odo, t, np.column_stack([x + drift[:, 0], y + drift[:, 1], np.zeros(n)]), yaw_to_quaternion(yaw))
    road = RoadMap.from_osm(d / "map.osm")
    k = slice(0, int(120 * RATE_HZ), int(RATE_HZ))
    lat, lon = road.projection.to_geo(x[k], y[k])
    gps = d / f"{name}_gps.csv"
    write_gps_csv(gps, t[k], lat, lon, sigma_m=np.full(len(lat), 2.0))
    return odo, gps


def peak_rss_mb(args: list[str]) -> float:
    """Peak RSS of ``mapfusion ARGS`` in a fresh process (MB)."""
    probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, capture_output=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", probe, sys.executable, "-m", "mapfusion.harness.cli", *args],
                         check=True, capture_output=True, text=True)
    return int(out.stdout.strip()) / 1024.0


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        b = OsmBuilder()
        a = np.linspace(0, 2 * math.pi, 181)
        b.way([(RADIUS_M * math.cos(v), RADIUS_M * math.sin(v)) for v in a], highway="primary", lanes=2)
        (d / "map.osm").write_text(b.to_xml())
        rss = {}
        for name, secs in (("10min", 600.0), ("2h", 7200.0)):
            odo, gps = write_drive(d, name, secs)
            rss[name] = peak_rss_mb(["fuse", "--map", str(d / "map.osm"), "--odometry", str(odo), "--gps", str(gps),
                                     "--out", str(d / f"{name}_est.tum"), "--smoothed", str(d / f"{name}_sm.tum")])
    row = {"benchmark": "fuse_memory", "peak_rss_10min_mb": round(rss["10min"], 1),
           "peak_rss_2h_mb": round(rss["2h"], 1), "ratio_2h_to_10min": round(rss["2h"] / rss["10min"], 3)}
    print(json.dumps(row))
    return 0 if row["ratio_2h_to_10min"] <= 1.10 else 1


if __name__ == "__main__":
    sys.exit(main())
