"""One road-particle filter step (issues 16, 17 and 21): ~30,000 particles started in a 182 m region of
Helsinki (the size of a road-fix restart), then 150 steps of 5 m along a slowly turning path, each followed
by the posterior's answer. Prints the time per step and a hash of every answer, so that two checkouts can
be compared for speed and for identical results:

Run:  PYTHONPATH=CHECKOUT python benchmarks/bench_particles.py      (once per checkout, same machine)
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import pickle
import time

import numpy as np

from mapfusion import RoadMap
from mapfusion.maps import resolve_map
from mapfusion.relocalise import Region, RoadParticles
from mapfusion.tracking import ROAD_FIX_PARAMS, particle_config


def main(steps: int = 150) -> None:
    road = RoadMap.from_osm(resolve_map("helsinki"))
    # the road fixes' own view of the filter, at a fixed count (no KLD-sampling) and the start's count as
    # when this benchmark was written (its answers' hash stays comparable across checkouts)
    cfg = dataclasses.replace(particle_config(ROAD_FIX_PARAMS), kld_epsilon=0.0, particles=60000)
    p = RoadParticles(road, cfg, 0)
    p.start(Region(81.0, -429.0, 182.0), 0.3, scale_range=(1 / 1.3, 1.3))
    answers = []
    t0 = time.perf_counter()
    for k in range(steps):
        yaw = 0.3 + 0.02 * k
        p.step(5.0, np.array([5.0 * math.cos(yaw), 5.0 * math.sin(yaw)]))
        loc = p.located(yaw)
        answers.append(None if loc is None else (loc.x_m, loc.y_m, loc.mass))
    dt = time.perf_counter() - t0
    digest = hashlib.md5(pickle.dumps(answers)).hexdigest()[:12]
    print(f"{len(p)} particles, {1000 * dt / steps:.2f} ms a step, answers {digest}")


if __name__ == "__main__":
    main()
