"""Runs in worker processes and on Dask: whole result lines, failures isolated, resume."""

from __future__ import annotations

import json
import os
import signal

import pytest

from mapfusion.harness.batch import ResultsLog, run_logged, run_many, run_one
from sim.scenario import scenario_from_dict

pytestmark = pytest.mark.sumo

METRIC_KEYS = ("ate_odometry_m", "ate_mapfusion_m", "online_rmse_mapfusion_m", "map_priors", "frames")


def _tiny(seed: int, name: str = "tiny"):
    return scenario_from_dict({"name": f"{name}-s{seed}", "map": "grid", "seed": seed, "duration_s": 150.0,
                               "min_route_m": 800.0, "weather": {"kind": "rain"}}, "test")


def _kill_seed_2(job):
    """A run whose process is killed outright (as by the OOM killer) while it works."""
    if job[0].seed == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return run_one(job)


def _count_and_run(job):
    with open(os.environ["RUN_COUNT_FILE"], "a") as f:
        f.write(job[0].name + "\n")
    return run_one(job)


def test_a_killed_run_costs_nothing_and_resume_reruns_only_it(tmp_path, monkeypatch):
    scs = [_tiny(s) for s in (1, 2, 3)]
    rows, ran = run_logged(scs, tmp_path, workers=2, plot=False, fn=_kill_seed_2)
    assert ran == 3
    by = {r["scenario"]: r for r in rows}
    assert "killed by signal 9" in by["tiny-s2"]["error"]
    assert "error" not in by["tiny-s1"] and "error" not in by["tiny-s3"]
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    assert len(lines) == 3 and all(json.loads(line) for line in lines)  # whole lines only
    count = tmp_path / "count.txt"
    monkeypatch.setenv("RUN_COUNT_FILE", str(count))
    rows, ran = run_logged(scs, tmp_path, workers=2, plot=False, fn=_count_and_run)
    assert ran == 1 and count.read_text().split() == ["tiny-s2"]
    assert all("error" not in r for r in rows) and len(rows) == 3
    # the first runs' lines are kept as they were; the re-run is appended
    assert (tmp_path / "results.jsonl").read_text().splitlines()[:3] == lines


def test_a_torn_last_line_is_ignored(tmp_path):
    p = tmp_path / "results.jsonl"
    p.write_text('{"scenario": "a", "x": 1}\n{"scenario": "b", "x"')
    log = ResultsLog(p)
    assert log.done() == {"a"}
    log.append({"scenario": "c"})
    assert [r["scenario"] for r in log.rows()] == ["a", "c"]  # the next line starts on a line of its own
    assert p.read_text().endswith('"x"\n{"scenario": "c"}\n')


@pytest.mark.slow
def test_dask_local_cluster_gives_the_process_pool_results():
    from dask.distributed import LocalCluster

    scs = [_tiny(s, "dask") for s in (1, 3)]
    local = run_many(scs, workers=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        remote = run_many(scs, scheduler=cluster.scheduler_address)
    assert len(local) == len(remote) == len(scs)
    assert [a["scenario"] for a in local] == [b["scenario"] for b in remote]
    for a, b in zip(local, remote):
        assert "error" not in a and "error" not in b, (a.get("error"), b.get("error"))
        for k in METRIC_KEYS:
            assert a[k] == b[k], k


def test_without_a_scheduler_dask_is_not_imported():
    import subprocess
    import sys

    code = ("import sys; from mapfusion.harness.batch import run_many; from sim.scenario import scenario_from_dict; "
            "sc = scenario_from_dict({'name': 'x', 'map': 'no-such-map.osm'}, 't', resolve=False); "
            "run_many([sc], workers=1); print('dask' in sys.modules, 'distributed' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
