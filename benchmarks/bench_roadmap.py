"""Road-map build time, radius-query time and match throughput on Helsinki and on a
10 km × 15 km synthetic city.

Targets: the city builds in under 20 s and a 20 m radius query takes under 20 µs, median
(issue 2); at least 50,000 matches per second on one core (issue 3).
Run:  python benchmarks/bench_roadmap.py      (or: mapfusion bench)
"""

from __future__ import annotations

import json
import sys

from mapfusion import RoadMap
from mapfusion.harness.bench import bench_match, bench_roadmap, big_city_map
from mapfusion.maps import resolve_map


def main() -> int:
    paths = [resolve_map("helsinki"), big_city_map()]
    results = [bench_roadmap(p) for p in paths]
    matches = [bench_match(RoadMap.from_osm(p)) for p in paths]
    for r in results + matches:
        print(json.dumps(r.to_dict()))
    city = results[1]
    ok = (city.build_s < 20.0 and all(r.query_median_us < 20.0 for r in results)
          and all(m.batch_matches_per_s >= 50000 for m in matches))
    print(f"city build {city.build_s:.2f} s (target < 20 s); median 20 m query "
          + ", ".join(f"{r.query_median_us:.1f} µs" for r in results) + " (target < 20 µs); matches/s "
          + ", ".join(f"{m.batch_matches_per_s:,.0f}" for m in matches) + " (target ≥ 50,000)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
