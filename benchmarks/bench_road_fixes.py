"""What the road fixes cost the engine (issues 16 and 21): ``bench_engine``'s drive (GPS for 120 s, then
odometry with a lateral drift) with the road fixes on and off, beside the bare GTSAM chain of the same
process, on the bench's synthetic grid city and on Helsinki. Prints one JSON object a line.

Run:  python benchmarks/bench_road_fixes.py [DURATION_S]      (default 600 s of driving)
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from mapfusion import FusionConfig, RoadMap
from mapfusion.harness.bench import bench_bare_chain, bench_engine, big_city_map
from mapfusion.maps import resolve_map


def main(duration_s: float = 600.0) -> None:
    with tempfile.TemporaryDirectory(prefix="mapfusion-bench-") as d:  # (the city's file: not left behind)
        roads = [("synthetic city 10 × 15 km", RoadMap.from_osm(big_city_map(Path(d)), cache=False))]
    roads.append(("helsinki", RoadMap.from_osm(resolve_map("helsinki"))))
    for name, road in roads:
        bare = bench_bare_chain(road, duration_s=duration_s)
        for label, cfg in (("on", FusionConfig()), ("off", FusionConfig(road_fixes=False))):
            e = bench_engine(road, duration_s=duration_s, config=cfg)
            print(json.dumps({"map": name, "road_fixes": label, "frames_per_s": e.frames_per_s, "growth": e.growth,
                              "bare_chain_frames_per_s": bare, "ratio_to_bare": e.frames_per_s / bare}), flush=True)


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 600.0)
