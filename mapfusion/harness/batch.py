"""Many runs at once: one process per run (libsumo runs one simulation per process), or a Dask
cluster; and ``results.jsonl``, appended a whole line at a time, which makes a sweep resumable.

A task is anything picklable handed to a module-level function that returns one result row (a
dict) or several (a list). A task that raises, or whose process dies (killed, out of memory,
a crash inside SUMO or GTSAM), becomes a failed row; it never costs the other tasks their rows.
"""

from __future__ import annotations

import errno
import gc
import json
import logging
import multiprocessing as mp
import os
import re
import signal
import traceback
from collections.abc import Callable, Iterable
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

from mapfusion.errors import InputError
from sim.scenario import Scenario

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- results.jsonl
class ResultsLog:
    """``results.jsonl``: one JSON object a line, appended with a single write per line (O_APPEND),
    so a run killed at any moment leaves whole lines; a torn last line from a dying machine is
    ignored on reading."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def rows(self) -> list[dict]:
        if not self.path.exists():
            return []
        out = []
        for i, line in enumerate(self.path.read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s:%d: not a whole JSON line, ignored", self.path, i)
        return out

    def done(self, key: Callable[[dict], str] = lambda r: r["scenario"]) -> set[str]:
        """Keys of the rows that finished without error (a failed run is run again on resume)."""
        return {key(r) for r in self.rows() if "error" not in r and "scenario" in r}

    def latest(self, key: Callable[[dict], str] = lambda r: r["scenario"]) -> dict[str, dict]:
        """The last row of every key."""
        return {key(r): r for r in self.rows() if "scenario" in r}

    def append(self, row: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = (json.dumps(row) + "\n").encode()
        fd = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            size = os.fstat(fd).st_size
            if size and os.pread(fd, 1, size - 1) != b"\n":
                data = b"\n" + data  # a line torn by a dying writer stays on its own line
            written = os.write(fd, data)
            if written < len(data):  # a full disk: the torn line is ignored on reading, the run stops
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
        finally:
            os.close(fd)


# ----------------------------------------------------------------------------- running tasks
def _failed(exc: BaseException) -> dict:
    return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=5)}


#: Errors of a full disk (or a file-size limit): they stop the whole batch, since every other run
#: would fail the same way; what finished is kept and the same command resumes.
DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _die_with_parent(parent_pid: int) -> None:
    """Linux: this worker gets SIGKILL when the process that started it dies (SIGKILL, SIGTERM, a
    crash), so no worker outlives ``run`` to race a resumed run for the same run directories."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: workers end with their task
        return
    if os.getppid() != parent_pid:  # the parent died before the call took effect
        os._exit(1)


def _child(conn, fn: Callable, task: Any, parent_pid: int) -> None:
    _die_with_parent(parent_pid)
    try:
        out = fn(task)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, never lost
        out = {"__failed__": _failed(exc)}
        if isinstance(exc, OSError) and exc.errno in DISK_FULL:
            out["__failed__"]["errno"], out["__failed__"]["filename"] = exc.errno, exc.filename
    try:
        conn.send(out)
    finally:
        conn.close()


def _as_rows(out: Any) -> list[dict]:
    return list(out) if isinstance(out, (list, tuple)) else [out]


def run_tasks(tasks: list[Any], fn: Callable[[Any], dict | list[dict]], workers: int = 2,
              on_rows: Callable[[Any, list[dict]], None] | None = None,
              on_failure: Callable[[Any, dict], None] | None = None,
              scheduler: str | None = None) -> None:
    """Run ``fn(task)`` for every task: ``workers`` processes at a time (one fresh process per task),
    or on the Dask cluster at ``scheduler``. ``on_rows(task, rows)`` receives each task's rows as it
    finishes; ``on_failure(task, {"error", "traceback"})`` a task that raised or whose process died."""
    on_rows = on_rows or (lambda task, rows: None)
    on_failure = on_failure or (lambda task, err: None)
    if scheduler:
        _run_dask(tasks, fn, scheduler, on_rows, on_failure)
        return
    ctx = mp.get_context("fork")
    # garbage a forked child would otherwise destroy holds no live lock or thread pool of this process
    # (a native thread pool destroyed in a child whose threads were not copied waits forever)
    gc.collect()
    pending = list(tasks)
    running: dict[Any, tuple] = {}  # pipe → (process, task)
    try:
        while pending or running:
            while pending and len(running) < max(1, workers):
                task = pending.pop(0)
                r, w = ctx.Pipe(duplex=False)
                p = ctx.Process(target=_child, args=(w, fn, task, os.getpid()), daemon=True)
                p.start()
                w.close()
                running[r] = (p, task)
            for r in wait(list(running)):
                p, task = running.pop(r)
                try:
                    out = r.recv()
                except (EOFError, OSError):  # the process died before it could answer
                    out = None
                r.close()
                p.join()
                if out is None:
                    code = p.exitcode
                    why = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                    on_failure(task, {"error": f"worker process died ({why})"})
                elif isinstance(out, dict) and "__failed__" in out:
                    if out["__failed__"].get("errno") in DISK_FULL:  # stop: the others would fail alike
                        code = out["__failed__"]["errno"]
                        raise OSError(code, os.strerror(code), out["__failed__"].get("filename"))
                    on_failure(task, out["__failed__"])
                else:
                    on_rows(task, _as_rows(out))
    finally:  # stopped early (a full disk, an interrupt): no worker is left running
        for p, _ in running.values():
            if p.is_alive():
                p.kill()
                p.join()


#: A Dask scheduler's address: TCP or TLS, host and port. Dask unpickles what the scheduler sends,
#: so a scheduler is trusted like code; no other transport is accepted.
_SCHEDULER = re.compile(r"(tcp|tls)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):([0-9]{1,5})")

#: Seconds to wait for the scheduler before giving up (before any run starts).
SCHEDULER_TIMEOUT_S = 10


def check_scheduler(address: str) -> str:
    """``address`` if it is ``tcp://HOST:PORT`` or ``tls://HOST:PORT``; an InputError otherwise."""
    m = _SCHEDULER.fullmatch(address)
    if not m or not 0 < int(m.group(3)) < 65536:
        raise InputError(f"--scheduler {address!r}: expected tcp://HOST:PORT or tls://HOST:PORT (a Dask scheduler; "
                         "it is trusted like code)")
    return address


def _run_dask(tasks, fn, scheduler, on_rows, on_failure) -> None:
    from dask.distributed import Client, as_completed  # only here: without --scheduler nothing of Dask loads

    check_scheduler(scheduler)
    try:
        client = Client(scheduler, timeout=SCHEDULER_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        raise InputError(f"--scheduler {scheduler}: cannot connect within {SCHEDULER_TIMEOUT_S} s "
                         f"({type(exc).__name__})") from None
    with client:
        futures = {client.submit(fn, task, pure=False): task for task in tasks}
        for fut in as_completed(futures):
            task = futures[fut]
            try:
                out = fut.result()
            except Exception as exc:  # the task raised, or its worker died (KilledWorker)
                on_failure(task, {"error": f"{type(exc).__name__}: {exc}"})
                continue
            on_rows(task, _as_rows(out))


# ----------------------------------------------------------------------------- scenario runs
def run_one(job: tuple[Scenario, str | None, bool]) -> dict:
    """One scenario end to end (a task of :func:`run_tasks`); bad input becomes a failed row. The
    run directory is written under a temporary name and renamed when complete, so a directory
    under its own name is always whole (a resumed run trusts it)."""
    import shutil

    from .pipeline import run_scenario

    sc, out_dir, plot = job
    digest = sc.content_hash()
    try:
        if out_dir is None:
            m = run_scenario(sc).metrics
        else:
            final = Path(out_dir) / sc.name
            partial = Path(out_dir) / f".{sc.name}.partial-{os.getpid()}"
            shutil.rmtree(partial, ignore_errors=True)
            m = run_scenario(sc, partial, plot=plot).metrics
            if final.exists():  # an earlier, stale or interrupted, run of this name
                shutil.rmtree(final)
            partial.rename(final)
    except InputError as exc:
        m = {"scenario": sc.name, "seed": sc.seed, "error": str(exc)}
    return {**m, "scenario_sha256": digest}


def remove_orphaned_partials(out_dir: str | Path) -> list[Path]:
    """Remove the partial run directories (``.NAME.partial-PID``) whose writing process is gone."""
    import shutil

    removed = []
    for d in Path(out_dir).glob(".*.partial-*"):
        try:
            os.kill(int(d.name.rsplit("-", 1)[1]), 0)
            continue  # still being written
        except ProcessLookupError:
            pass
        except (ValueError, PermissionError):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def plan_runs(scenarios: Iterable[Scenario], results_path: str | Path) -> tuple[list[Scenario], list[str]]:
    """The scenarios ``results.jsonl`` has no finished row for, with this very content (name and
    :meth:`Scenario.content_hash`), and the names among them whose finished row is of an earlier
    content (the scenario file or its engine configuration was edited since)."""
    finished: dict[str, set] = {}
    for r in ResultsLog(results_path).rows():
        if "error" not in r and "scenario" in r:
            finished.setdefault(r["scenario"], set()).add(r.get("scenario_sha256"))
    todo = [sc for sc in scenarios if sc.content_hash() not in finished.get(sc.name, set())]
    return todo, [sc.name for sc in todo if sc.name in finished]


def _preload(fn: Callable, scheduler: str | None) -> None:
    """Import the pipeline (GTSAM, SUMO, the engine: about a second) once in this process, so that every
    forked worker inherits it instead of importing it again per run (issue 21). Dask workers are
    separate processes: nothing to share."""
    if scheduler is None and fn is run_one:
        from . import pipeline  # noqa: F401


def run_many(scenarios: Iterable[Scenario], workers: int = 2, out_dir: str | Path | None = None, plot: bool = False,
             on_result: Callable[[dict], None] | None = None, scheduler: str | None = None,
             fn: Callable = run_one) -> list[dict]:
    """Metrics of every scenario, in the given order; ``on_result(row)`` as each finishes (a failed
    run is a row with ``error``)."""
    scenarios = list(scenarios)
    by_name: dict[str, dict] = {}

    def rows(job, rs):
        for r in rs:
            by_name[job[0].name] = r
            if on_result:
                on_result(r)

    def failed(job, err):
        rows(job, [{"scenario": job[0].name, "seed": job[0].seed, **err}])

    jobs = [(sc, None if out_dir is None else str(out_dir), plot) for sc in scenarios]
    _preload(fn, scheduler)
    run_tasks(jobs, fn, workers=workers, on_rows=rows, on_failure=failed, scheduler=scheduler)
    return [by_name[sc.name] for sc in scenarios]


def run_logged(scenarios: Iterable[Scenario], out_dir: str | Path, workers: int = 2, plot: bool = True,
               scheduler: str | None = None, on_row: Callable[[dict], None] | None = None,
               fn: Callable = run_one) -> tuple[list[dict], int]:
    """The runs of ``scenarios`` not yet finished in ``out_dir/results.jsonl`` (resume), each row
    appended as it finishes. Returns the latest row of every scenario and how many ran now."""
    scenarios = list(scenarios)
    results = ResultsLog(Path(out_dir) / "results.jsonl")
    todo, _ = plan_runs(scenarios, results.path)
    remove_orphaned_partials(out_dir)

    def finished(job, rows):
        for row in rows:
            results.append(row)
            if on_row:
                on_row(row)

    def failed(job, err):
        finished(job, [{"scenario": job[0].name, "seed": job[0].seed, "scenario_sha256": job[0].content_hash(), **err}])

    _preload(fn, scheduler)
    run_tasks([(sc, str(out_dir), plot) for sc in todo], fn, workers=workers, on_rows=finished,
              on_failure=failed, scheduler=scheduler)
    current = {(sc.name, sc.content_hash()) for sc in scenarios}
    latest = {r["scenario"]: r for r in results.rows() if (r.get("scenario"), r.get("scenario_sha256")) in current}
    return [latest[sc.name] for sc in scenarios if sc.name in latest], len(todo)
