"""Engine throughput on a one-hour drive at 10 Hz with map priors, fixed-lag backend, on the
10 km × 15 km city. Targets (issue 6): ≥ 2,000 frames/s on one core, and the time per frame over
the last 10% of the drive within 1.2× of the first 10%. Run: python benchmarks/bench_engine.py"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from mapfusion import RoadMap
from mapfusion.harness.bench import bench_engine, big_city_map

if __name__ == "__main__":
    with tempfile.TemporaryDirectory(prefix="mapfusion-bench-") as d:
        road = RoadMap.from_osm(big_city_map(Path(d)))
    b = bench_engine(road, duration_s=3600.0)
    print(json.dumps(b.to_dict()))
    sys.exit(0 if b.frames_per_s >= 2000 and b.growth <= 1.2 else 1)
