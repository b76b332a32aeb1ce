"""Issue 18's calibration figure: a wheel 2% too fast, GPS (1 Hz, σ 2 m) for the first GPS_S seconds
of a SUMO city drive; how far the engine's wheel scale is from the truth.

    python benchmarks/measure_wheel_scale.py --gps-s 60 --seeds 6

One line per drive (Helsinki and Kotka, clear weather, vo+wheel) and the largest error.
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gps-s", type=float, default=60.0, help="seconds of GPS from the start")
    ap.add_argument("--seeds", type=int, default=6, help="seeds 1..N on each map")
    ap.add_argument("--duration-s", type=float, default=200.0, help="length of each drive")
    args = ap.parse_args()

    from mapfusion.harness.pipeline import fixes_of, motion_of, simulate_scenario
    from mapfusion.replay import fuse
    from sim.scenario import scenario_from_dict

    errors = []
    for seed in range(1, args.seeds + 1):
        for city in ("helsinki", "kotka"):
            sc = scenario_from_dict({"name": f"wheel-{city}-s{seed}", "map": city, "seed": seed,
                                     "duration_s": args.duration_s, "odometry": {"kind": "vo+wheel"},
                                     "gps": {"mode": "init_only", "init_window_s": args.gps_s},
                                     "wheel": {"scale_error_min": 0.02, "scale_error_max": 0.02}}, "measure")
            sim = simulate_scenario(sc)
            odo = sim.sensors.odometry
            res = fuse(sim.road, odo.t_s, odo.poses, fixes_of(sim.sensors, sim.road), sc.mapfusion,
                       motion=motion_of(sim.sensors))
            true = 1.0 / (1.0 + sim.sensors.wheel.scale_error)
            early = sim.truth.t_s <= args.gps_s
            driven = float(np.sum(np.hypot(np.diff(sim.truth.x_m[early]), np.diff(sim.truth.y_m[early]))))
            err = 100.0 * (res.engine.wheel_scale / true - 1.0)
            errors.append(abs(err))
            print(f"{city} seed {seed}: {driven:5.0f} m driven with GPS; wheel scale {res.engine.wheel_scale:.5f}, "
                  f"true {true:.5f}: {err:+.3f} %", flush=True)
    print(f"within 0.3 %: {sum(e <= 0.3 for e in errors)} of {len(errors)}; largest |error| {max(errors):.3f} %")


if __name__ == "__main__":
    main()
