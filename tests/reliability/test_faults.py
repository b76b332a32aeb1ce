"""Faults (issue 19): a killed or terminated ``run`` leaves no worker behind and resumes to whole run
directories; a full disk stops a run cleanly and the resume completes; an edited scenario is run
again on resume; a tune trial killed mid-way is marked failed on resume."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.sumo, pytest.mark.slow]

FAMILY = """[family]
name = "fault"
seeds = [1, 2, 3]
[base]
map = "grid"
duration_s = 150.0
min_route_m = 1000.0
[base.gps]
mode = "continuous"
"""


#: Drives long enough (≈ 8 s of work each) that a worker is still busy when its parent is stopped.
LONG_FAMILY = FAMILY.replace("seeds = [1, 2, 3]", "seeds = [1, 2]").replace("150.0", "500.0").replace("1000.0", "4000.0")


def _cli(*args: str, **kw) -> list[str]:
    return [sys.executable, "-m", "mapfusion.harness.cli", *args]


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _rows(out: Path) -> list[dict]:
    p = out / "results.jsonl"
    if not p.exists():
        return []
    rows = []
    for line in p.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return rows


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
def test_workers_die_with_their_parent_and_the_run_resumes(tmp_path, sig):
    fam = tmp_path / "fam.toml"
    fam.write_text(LONG_FAMILY)
    out = tmp_path / "out"
    cmd = _cli("run", str(fam), "--out", str(out), "-j", "2", "--no-plot")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    workers: list[int] = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not workers:
        workers = _children(proc.pid)
        time.sleep(0.02)
    assert workers, "no worker process started"
    time.sleep(0.3)  # both workers are inside their SUMO drives
    workers = sorted(set(workers) | set(_children(proc.pid)))
    proc.send_signal(sig)
    proc.wait(timeout=30)
    deadline = time.monotonic() + 2  # a worker's drive has seconds of work left: only the signal ends it now
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.05)
    assert not [w for w in workers if _alive(w)], "a worker outlived its parent"
    # the resume completes every run, each run directory whole, no partial one left behind
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    ok = {row["scenario"] for row in _rows(out) if "error" not in row}
    assert ok == {"fault-s1", "fault-s2"}
    for name in ok:
        assert (out / name / "metrics.json").exists() and (out / name / "estimate_mapfusion.tum").exists()
    assert not list(out.glob(".*partial*"))


def _limit_file_size(limit: int):
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_full_disk_stops_cleanly_and_the_resume_completes(tmp_path):
    """A file-size limit makes every write past 150 kB fail as a full disk does (EFBIG, like ENOSPC):
    the run stops with one line and exit 1, nothing torn is trusted, and without the limit the same
    command finishes every run."""
    fam = tmp_path / "fam.toml"
    fam.write_text(FAMILY)
    out = tmp_path / "out"
    cmd = _cli("run", str(fam), "--out", str(out), "-j", "2", "--no-plot")
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, preexec_fn=_limit_file_size(150_000))
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "resumes" in lines[0] and ("too large" in lines[0] or "space" in lines[0]), lines[0]
    assert not [row for row in _rows(out) if "error" not in row]  # no run could finish its files
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert {row["scenario"] for row in _rows(out) if "error" not in row} == {f"fault-s{s}" for s in (1, 2, 3)}
    assert not list(out.glob(".*partial*"))


def test_an_edited_scenario_is_run_again_on_resume(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text('name = "edit"\nmap = "grid"\nseed = 4\nduration_s = 150.0\nmin_route_m = 1000.0\n'
                  '[gps]\nmode = "continuous"\n')
    out = tmp_path / "out"
    cmd = _cli("run", str(sc), "--out", str(out), "--no-plot")
    assert subprocess.run(cmd, capture_output=True, timeout=600).returncode == 0
    first = _rows(out)
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)  # unchanged: skipped
    assert r.returncode == 0 and "resuming: 1 of 1" in r.stderr and len(_rows(out)) == 1
    sc.write_text(sc.read_text().replace('"continuous"', '"interval"') + '[weather]\nkind = "heavy_rain"\n')
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "running again 1 run" in r.stderr, r.stderr
    rows = _rows(out)
    assert len(rows) == 2 and rows[1]["weather"] == "heavy_rain" and rows[1]["gps_mode"] == "interval"
    assert rows[1]["scenario_sha256"] != first[0]["scenario_sha256"]
    assert 'kind = "heavy_rain"' in (out / "edit" / "scenario.toml").read_text()


def test_a_killed_tune_trial_is_marked_failed_on_resume(tmp_path):
    import optuna
    from optuna.trial import TrialState

    sc = tmp_path / "t.toml"
    sc.write_text('name = "tune"\nmap = "grid"\nseed = 2\nduration_s = 150.0\nmin_route_m = 1000.0\n'
                  '[gps]\nmode = "continuous"\n')
    out = tmp_path / "study"
    url = f"sqlite:///{out / 'study.db'}"
    cmd = _cli("tune", str(sc), "--out", str(out), "--study", "s")
    err = tmp_path / "tune.err"
    with err.open("w") as err_file:
        proc = subprocess.Popen([*cmd, "--trials", "200"], stdout=subprocess.DEVNULL, stderr=err_file,
                                start_new_session=True)

    def states() -> list:
        try:
            return [t.state for t in optuna.load_study(study_name="s", storage=url).trials]
        except Exception:  # noqa: BLE001 - the study is not there yet
            return []

    def watched() -> list:
        # While the tune runs, read without Optuna: its storage would create the tables the tune is
        # creating at the same moment (a race the tune survives, but the watcher need not take part).
        db = out / "study.db"
        if not db.exists():
            return []
        try:
            with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)) as con:
                rows = con.execute("SELECT t.state FROM trials t JOIN studies s ON t.study_id = s.study_id "
                                   "WHERE s.study_name = 's'").fetchall()
        except sqlite3.Error:  # not created yet, or mid-write
            return []
        return [TrialState[r[0]] for r in rows]

    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and not {TrialState.COMPLETE, TrialState.RUNNING} <= set(watched()):
        if proc.poll() is not None:
            pytest.fail(f"the tune ended on its own (exit {proc.returncode}) before it could be killed: "
                        f"{err.read_text()[-400:]}")
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    before = states()
    for _ in range(50):  # (a reader can meet the database mid-recovery from the kill: read it again)
        if before:
            break
        time.sleep(0.1)
        before = states()
    assert TrialState.RUNNING in before, f"the tune was not killed inside a trial: {before}"
    r = subprocess.run([*cmd, "--trials", "1"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    after = states()
    assert TrialState.RUNNING not in after
    assert after.count(TrialState.FAIL) >= before.count(TrialState.RUNNING)
    assert after.count(TrialState.COMPLETE) == before.count(TrialState.COMPLETE) + 1


def test_an_unreachable_scheduler_is_one_line_and_exit_2(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text('name = "sched"\nmap = "grid"\nseed = 1\nduration_s = 30.0\n')
    start = time.monotonic()
    r = subprocess.run(_cli("run", str(sc), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:1"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--scheduler" in lines[0] and "Traceback" not in r.stderr
    assert time.monotonic() - start < 30  # refused well before any run could start
    assert not list((tmp_path / "o").glob("*"))
