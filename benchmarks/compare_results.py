"""Do two revisions give the same results? (issue 21: speed-ups must leave every result unchanged)

Simulates drives of six families once (with this checkout's simulator), then fuses each under both
revisions' engines (a git worktree each, run in a fresh process) with three configurations — the
defaults, centre-line and band priors — and compares every
smoothed and online pose and every metric. Prints the largest difference; exits 1 if any exceeds 1e-9.

Run from the repo root: python benchmarks/compare_results.py c5e51d6 [HEAD]   (MAPFUSION_DATA set)
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

FAMILIES = [("intersections", [0, 3, 5, 9, 12]), ("rain-tunnel", [0, 2, 4, 7]), ("kitti", [0, 3, 9]),
            ("heavy-rain", [0, 1]), ("rain", [1, 4]), ("kidnapped", [0, 2, 5, 7])]
REPO = Path(__file__).resolve().parents[1]


def simulate(out: Path) -> None:
    from mapfusion.harness.pipeline import simulate_scenario
    from sim.scenario import load_family

    sims = []
    for fam, idx in FAMILIES:
        scenarios = load_family(REPO / "scenarios" / "families" / f"{fam}.toml").scenarios
        sims += [dataclasses.replace(simulate_scenario(scenarios[i]), road=None) for i in idx if i < len(scenarios)]
    out.write_bytes(pickle.dumps(sims))


def fuse(sims_path: Path, out: Path) -> None:
    from mapfusion import RoadMap
    from mapfusion.config import PriorTarget
    from mapfusion.harness.pipeline import fuse_and_evaluate

    configs = {"default": {}, "centre": {"prior_target": PriorTarget.centre},
               "band": {"prior_target": PriorTarget.band}}
    res = {}
    for s in pickle.loads(sims_path.read_bytes()):
        s = dataclasses.replace(s, road=RoadMap.from_osm(s.sc.map))
        for name, kw in configs.items():
            m, _, mf = fuse_and_evaluate(s, dataclasses.replace(s.sc.mapfusion, **kw))
            smoothed = np.array([[t, p.x(), p.y(), p.rotation().yaw()] for t, p in mf.engine.trajectory().items()])
            online = np.array([[p.x(), p.y()] if p is not None else [np.nan, np.nan]
                               for p in mf.engine.online_estimates()[1]])
            metrics = {k: v for k, v in m.items() if isinstance(v, (int, float)) and "per_s" not in k}
            res[f"{s.sc.name}|{name}"] = (smoothed, online, metrics)
    out.write_bytes(pickle.dumps(res))


def compare(a: dict, b: dict) -> float:
    worst = 0.0
    for key, (sa, oa, ma) in a.items():
        sb, ob, mb = b[key]
        if sa.shape != sb.shape or oa.shape != ob.shape or set(ma) != set(mb):
            print(f"{key}: a different number of poses or metrics")
            return float("inf")
        d = max([float(np.nanmax(np.abs(sa - sb))) if sa.size else 0.0,
                 float(np.nanmax(np.abs(oa - ob))) if oa.size else 0.0]
                + [abs(ma[k] - mb[k]) for k in ma if ma[k] is not None and mb[k] is not None])
        if d > 1e-9:
            print(f"{key}: differs by {d:.3g}")
        worst = max(worst, d)
    return worst


def main(old: str, new: str = "HEAD") -> int:
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        simulate(t / "sims.pkl")
        results = []
        for i, rev in enumerate((old, new)):
            tree = t / f"tree{i}"
            subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), rev], check=True,
                           capture_output=True)
            try:
                env = dict(os.environ, PYTHONPATH=str(tree))
                subprocess.run([sys.executable, __file__, "--fuse", str(t / "sims.pkl"), str(t / f"res{i}.pkl")],
                               check=True, env=env, cwd=tree)
            finally:
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
            results.append(pickle.loads((t / f"res{i}.pkl").read_bytes()))
        worst = compare(*results)
        print(f"{len(results[0])} fusions compared, {old} against {new}: largest difference {worst:.3g}")
        return 0 if worst <= 1e-9 else 1


if __name__ == "__main__":
    if sys.argv[1:2] == ["--fuse"]:
        fuse(Path(sys.argv[2]), Path(sys.argv[3]))
    else:
        sys.exit(main(*sys.argv[1:3]))
