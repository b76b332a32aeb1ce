"""The noise floor of a scenario family: how far a run's result moves when nothing but the last bits move.

Each run is simulated once; its recorded inputs (odometry poses, GPS fixes, wheel speed, gyro) are then
fused again with every value multiplied by ``1 + rel·N(0, 1)`` (``rel`` 1e-12 by default, seeded per run
and draw), and the same unperturbed inputs are fused under other math-library code paths (glibc's
hardware-capability selection, numpy's CPU dispatch), each in a fresh process. What moves between these
fusions is the engine's sensitivity to the last bits: what a machine with another CPU sees.

``scenarios/noise_floor.json`` holds, per run, the ATE of every fusion; ``scenarios/test_families.py``
takes its per-run tolerances from it (:func:`run_tolerance_m`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import sys
import tempfile
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from sim.scenario import Scenario

log = logging.getLogger(__name__)

#: Relative size of the perturbation: about 5,000 units in the last place of a double.
PERTURB_REL = 1e-12

#: The glibc setting that imitates a CPU without AVX2, FMA and AVX-512 (libm and the string functions
#: pick other code for exp, log, sin, pow ...).
GLIBC_OTHER_CPU = "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F"

#: The metrics a draw keeps.
KEYS = ("ate_odometry_m", "ate_mapfusion_m", "delocalized_odometry", "delocalized_mapfusion", "match_rate",
        "tunnel_rmse_mapfusion_m")


def numpy_features_off() -> str:
    """The value of ``NPY_DISABLE_CPU_FEATURES`` that turns off every AVX-512 feature numpy dispatches to
    on this machine; on a machine without AVX-512, every feature numpy dispatches to beyond its baseline
    (so that the setting still moves numpy onto other code)."""
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__

    found = [f for f in __cpu_dispatch__ if __cpu_features__.get(f) and f not in __cpu_baseline__]
    avx512 = [f for f in found if "AVX512" in f or f == "X86_V4"]
    return ",".join(avx512 or found)


def code_paths() -> dict[str, dict[str, str]]:
    """Name → environment of every other code path a noise floor fuses under."""
    paths = {"glibc": {"GLIBC_TUNABLES": GLIBC_OTHER_CPU}}
    npy = numpy_features_off()
    if npy:
        paths["numpy"] = {"NPY_DISABLE_CPU_FEATURES": npy}
    return paths


def parse_params(specs: Iterable[str]) -> dict:
    """``KEY=VALUE`` strings as a [mapfusion] table, each value read as a TOML value (else kept a string);
    ValueError on a spec without ``=``."""
    import tomllib

    out = {}
    for spec in specs:
        key, sep, value = spec.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{spec!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = value
    return out


def with_engine_params(scenarios: Iterable[Scenario], params: dict, where: str = "--param") -> list[Scenario]:
    """The scenarios with these engine parameters changed (a ConfigError names a bad one)."""
    from .sweep import with_params

    return [dataclasses.replace(sc, mapfusion=with_params(sc.mapfusion, params, where)) for sc in scenarios]


def _times(a: np.ndarray, rng: np.random.Generator, rel: float) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a * (1.0 + rel * rng.standard_normal(a.shape))


def perturbed(sensors, rel: float, rng: np.random.Generator):
    """``sensors`` (a :class:`sim.sensors.SensorData`) with every recorded value the engine reads multiplied
    by ``1 + rel·N(0, 1)``: the odometry poses' rotation and translation entries, the fixes' position and
    altitude, the wheel speeds and the gyro rates. Times, σ's and the truth are left as they are."""
    odo = sensors.odometry
    poses = np.array(odo.poses, dtype=float, copy=True)
    poses[:, :3, :] = _times(poses[:, :3, :], rng, rel)
    g = sensors.gps
    gps = dataclasses.replace(g, x_m=_times(g.x_m, rng, rel), y_m=_times(g.y_m, rng, rel),
                              alt_m=_times(g.alt_m, rng, rel))
    imu = dataclasses.replace(sensors.imu, gyro_radps=_times(sensors.imu.gyro_radps, rng, rel))
    wheel = sensors.wheel
    if wheel is not None:
        wheel = dataclasses.replace(wheel, speed_mps=_times(wheel.speed_mps, rng, rel))
    return dataclasses.replace(sensors, odometry=dataclasses.replace(odo, poses=poses), gps=gps, imu=imu, wheel=wheel)


def draw_seed(name: str, seed: int, draw: int) -> int:
    """The perturbation's seed of one draw of one run (stable across processes and machines)."""
    return (zlib.crc32(name.encode()) * 1_000_003 + seed * 1009 + draw) % (2**63)


def noise_task(job: tuple[Scenario, int, float, int]) -> list[dict]:
    """One scenario simulated once and fused ``1 + draws`` times: draw 0 on its own inputs, draws 1..n
    perturbed (a task of :func:`mapfusion.harness.batch.run_tasks`); a row a fusion."""
    from .pipeline import fuse_and_evaluate, simulate_scenario

    sc, draws, rel, seed = job
    sim = simulate_scenario(sc)
    rows = []
    for d in range(draws + 1):
        s = sim if d == 0 else dataclasses.replace(
            sim, sensors=perturbed(sim.sensors, rel, np.random.default_rng(draw_seed(sc.name, seed, d))))
        m, _, _ = fuse_and_evaluate(s, sc.mapfusion)
        row = {"scenario": sc.name, "draw": d}
        if "error" in m:
            row["error"] = m["error"]
        else:
            row.update({k: m.get(k) for k in KEYS})
        rows.append(row)
    return rows


def measure(scenarios: list[Scenario], draws: int = 5, rel: float = PERTURB_REL, seed: int = 0, workers: int = 2,
            on_rows: Callable[[list[dict]], None] | None = None) -> list[dict]:
    """Every scenario's fusions (see :func:`noise_task`), a run at a time on ``workers`` processes; a failed
    run is a row with ``error`` and never costs the others theirs."""
    from .batch import run_tasks

    out: list[dict] = []

    def got(job, rows):
        out.extend(rows)
        if on_rows:
            on_rows(rows)

    def failed(job, err):
        row = {"scenario": job[0].name, "draw": None, "error": err["error"]}
        out.append(row)
        if on_rows:
            on_rows([row])

    run_tasks([(sc, draws, rel, seed) for sc in scenarios], noise_task, workers=workers, on_rows=got,
              on_failure=failed)
    return out


def measure_under(env: dict[str, str], family_paths: list[Path], workers: int, params: list[str] = ()) -> list[dict]:
    """The unperturbed fusions (draw 0) of the families' runs in a fresh Python process whose environment
    adds ``env`` (a code path is picked when a library loads: it cannot be changed inside this process)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        cmd = [sys.executable, "-m", "mapfusion.harness.noise", "--draws", "0", "--workers", str(workers),
               "--rows", str(out), *[a for p in params for a in ("--param", p)], *map(str, family_paths)]
        subprocess.run(cmd, env={**os.environ, **env}, check=True)
        return json.loads(out.read_text())


def summarise(rows: Iterable[dict], other: dict[str, list[dict]], families: dict[str, str], rel: float,
              draws: int) -> dict:
    """The noise-floor document: per run, the ATEs of its draws and of its other code paths, and its range."""
    runs: dict[str, dict] = {}
    for r in rows:
        if "error" in r:
            runs.setdefault(r["scenario"], {})["error"] = r["error"]
            continue
        e = runs.setdefault(r["scenario"], {"family": families.get(r["scenario"]), "draws": {k: [] for k in KEYS}})
        if "draws" not in e:
            continue
        for k in KEYS:
            e["draws"][k].append(r[k])
    for name, rs in other.items():
        for r in rs:
            if r["scenario"] in runs and "error" not in r and "draws" in runs[r["scenario"]]:
                runs[r["scenario"]].setdefault("code_paths", {})[name] = {k: r[k] for k in KEYS}
    for e in runs.values():
        if "draws" in e:
            e.update(spread_of(e))
    return {"rel": rel, "draws": draws, "code_paths": {k: v for k, v in code_paths().items() if k in other},
            "runs": dict(sorted(runs.items()))}


def all_ates(entry: dict, key: str = "ate_mapfusion_m") -> list[float]:
    """Every ATE of a run's noise-floor entry: its draws and its code paths."""
    return [float(a) for a in entry["draws"][key]] + [float(c[key]) for c in entry.get("code_paths", {}).values()]


def spread_of(entry: dict) -> dict:
    """A run's range of Map-Fusion ATE over its fusions, in metres and relative to their median; and whether
    its de-localisation flips between them."""
    a = np.array(all_ates(entry))
    deloc = list(entry["draws"]["delocalized_mapfusion"]) + [c["delocalized_mapfusion"]
                                                             for c in entry.get("code_paths", {}).values()]
    med = float(np.median(a))
    return {"range_m": float(a.max() - a.min()), "spread": float((a.max() - a.min()) / med) if med > 0 else 0.0,
            "delocalized_flips": len(set(deloc)) > 1}


#: The smallest per-run tolerance (m): a run whose fusions agree to the bit still gets this much.
MIN_TOLERANCE_M = 0.05
#: A run's tolerance in ranges of its measured fusions: the range of six fusions understates the noise (a
#: seventh lands outside it about 2 times in 7), so a run may move up to twice that range beyond its baseline.
RANGE_FACTOR = 2.0


def run_tolerance_m(entry: dict | None, baseline_m: float) -> float:
    """How far above its baseline a run's Map-Fusion ATE may land before it counts as a regression: twice the
    measured range of its fusions (at least :data:`MIN_TOLERANCE_M`); without a noise floor, 10%."""
    if entry is None or "draws" not in entry:
        return max(0.25, 0.10 * baseline_m)
    return max(MIN_TOLERANCE_M, RANGE_FACTOR * entry["range_m"])


def _main(argv: list[str] | None = None) -> int:
    """``python -m mapfusion.harness.noise [--draws N] [--rows FILE] FAMILY...``: what
    :func:`measure_under` runs in a fresh process."""
    import argparse

    from sim.scenario import load_family

    ap = argparse.ArgumentParser(prog="python -m mapfusion.harness.noise")
    ap.add_argument("families", nargs="+", type=Path)
    ap.add_argument("--draws", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rows", type=Path, required=True)
    ap.add_argument("--param", action="append", default=[])
    a = ap.parse_args(argv)
    scenarios = [sc for p in a.families for sc in load_family(p).scenarios]
    if a.param:
        scenarios = with_engine_params(scenarios, parse_params(a.param))
    rows = measure(scenarios, draws=a.draws, workers=a.workers)
    a.rows.write_text(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
