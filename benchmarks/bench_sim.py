"""Simulated seconds per wall second on Helsinki: the ego alone, and with 200 vehicles
(recording only the ego, and in fleet mode recording all). Run: python benchmarks/bench_sim.py"""

from __future__ import annotations

import json

from mapfusion.harness.bench import bench_sim

if __name__ == "__main__":
    for n, fleet in ((0, False), (200, False), (200, True)):
        print(json.dumps(bench_sim(n, fleet).to_dict()))
