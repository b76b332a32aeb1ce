"""Road-map build time and radius-query time on Helsinki and on a 10 km × 15 km synthetic city.

Targets (issue 2): the city builds in under 20 s; a 20 m radius query takes under 20 µs (median).
Run:  python benchmarks/bench_roadmap.py      (or: mapfusion bench)
"""

from __future__ import annotations

import json
import sys

from mapfusion.bench import bench_roadmap, big_city_map
from mapfusion.maps import resolve_map


def main() -> int:
    results = [bench_roadmap(resolve_map("helsinki")), bench_roadmap(big_city_map())]
    for r in results:
        print(json.dumps(r.to_dict()))
    city = results[1]
    ok = city.build_s < 20.0 and all(r.query_median_us < 20.0 for r in results)
    print(f"city build {city.build_s:.2f} s (target < 20 s); median 20 m query "
          + ", ".join(f"{r.query_median_us:.1f} µs" for r in results) + " (target < 20 µs)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
