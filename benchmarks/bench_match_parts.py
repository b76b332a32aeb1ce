"""Where a single match's time goes (issue 21): on the poses of ``bench_match`` (near random way-points, 3 m
and 0.2 rad off), the whole ``RoadMap.match``, a k-d tree ball query of the same radius, and the match's parts
(the cell index's slices, the scoring of the candidates, building the ``Match``), each timed in turns, 250
poses at a time; medians of the turns, in µs a call. Prints one JSON object.

Run:  python benchmarks/bench_match_parts.py [MAP]      (default helsinki; a built-in name or an OSM file)
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from mapfusion.matcher import DEFAULT_RADIUS_M, _best, _make_match
from mapfusion.roadmap import load_roadmap


def main(map_name: str = "helsinki", n: int = 5000, chunk: int = 250) -> dict:
    road = load_roadmap(map_name)
    rng = np.random.default_rng(0)
    i = rng.integers(0, len(road), n)
    x = (road.xy_m[i, 0] + rng.normal(0, 3, n)).tolist()
    y = (road.xy_m[i, 1] + rng.normal(0, 3, n)).tolist()
    yaw = (road.yaw_rad[i] + rng.normal(0, 0.2, n)).tolist()
    points, r = np.column_stack([x, y]), DEFAULT_RADIUS_M
    cells = road.cells
    sl = [cells.slices(x[j], y[j], r) for j in range(n)]
    parts = [(cells.gather(cells.z, s), *cells.gather(cells.block, s)) for s in sl]
    found = [_best(*p, x[j], y[j], yaw[j], 1.0, r) for j, p in enumerate(parts)]

    def whole(j):
        road.match(x[j], y[j], yaw[j])

    def kdtree(j):
        road.tree.query_ball_point(points[j], r)

    def slices(j):
        s = cells.slices(x[j], y[j], r)
        cells.gather(cells.z, s), cells.gather(cells.block, s)

    def scoring(j):
        _best(*parts[j], x[j], y[j], yaw[j], 1.0, r)

    def building(j):
        if found[j] is not None:
            k, rev, e, a, d = found[j]
            _make_match(road, cells.point_of(sl[j], k), rev, x[j], y[j], e, a, d)

    steps = {"match": whole, "kdtree": kdtree, "slices": slices, "scoring": scoring, "building": building}
    spent: dict[str, list[float]] = {k: [] for k in steps}
    for a in range(0, n, chunk):
        for name, f in steps.items():
            t0 = time.perf_counter()
            for j in range(a, min(a + chunk, n)):
                f(j)
            spent[name].append((time.perf_counter() - t0) / (min(a + chunk, n) - a) * 1e6)
    out = {"map": str(map_name), "candidates_mean": float(np.mean([len(p[0]) for p in parts]))}
    out.update({f"{k}_us": float(np.median(v)) for k, v in spent.items()})
    out["single_ratio_to_kdtree"] = float(np.median(np.array(spent["kdtree"]) / np.array(spent["match"])))
    return out


if __name__ == "__main__":
    print(json.dumps(main(*sys.argv[1:2])))
