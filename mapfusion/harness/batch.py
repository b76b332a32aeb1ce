"""Many runs at once: one process per run (libsumo runs one simulation per process), or a Dask
cluster; and ``results.jsonl``, appended a whole line at a time, which makes a sweep resumable.

A task is anything picklable handed to a module-level function that returns one result row (a
dict) or several (a list). A task that raises, or whose process dies (killed, out of memory,
a crash inside SUMO or GTSAM), becomes a failed row; it never costs the other tasks their rows.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import traceback
from collections.abc import Callable, Iterable
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

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
            os.write(fd, data)
        finally:
            os.close(fd)


# ----------------------------------------------------------------------------- running tasks
def _failed(exc: BaseException) -> dict:
    return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=5)}


def _child(conn, fn: Callable, task: Any) -> None:
    try:
        out = fn(task)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, never lost
        out = {"__failed__": _failed(exc)}
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
    pending = list(tasks)
    running: dict[Any, tuple] = {}  # pipe → (process, task)
    while pending or running:
        while pending and len(running) < max(1, workers):
            task = pending.pop(0)
            r, w = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_child, args=(w, fn, task), daemon=True)
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
                on_failure(task, out["__failed__"])
            else:
                on_rows(task, _as_rows(out))


def _run_dask(tasks, fn, scheduler, on_rows, on_failure) -> None:
    from dask.distributed import Client, as_completed  # only here: without --scheduler nothing of Dask loads

    with Client(scheduler) as client:
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
    """One scenario end to end (a task of :func:`run_tasks`); bad input becomes a failed row."""
    from mapfusion.errors import InputError

    from .pipeline import run_scenario

    sc, out_dir, plot = job
    try:
        return run_scenario(sc, None if out_dir is None else Path(out_dir) / sc.name, plot=plot).metrics
    except InputError as exc:
        return {"scenario": sc.name, "seed": sc.seed, "error": str(exc)}


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
    run_tasks(jobs, fn, workers=workers, on_rows=rows, on_failure=failed, scheduler=scheduler)
    return [by_name[sc.name] for sc in scenarios]


def run_logged(scenarios: Iterable[Scenario], out_dir: str | Path, workers: int = 2, plot: bool = True,
               scheduler: str | None = None, on_row: Callable[[dict], None] | None = None,
               fn: Callable = run_one) -> tuple[list[dict], int]:
    """The runs of ``scenarios`` not yet finished in ``out_dir/results.jsonl`` (resume), each row
    appended as it finishes. Returns the latest row of every scenario and how many ran now."""
    scenarios = list(scenarios)
    results = ResultsLog(Path(out_dir) / "results.jsonl")
    done = results.done()
    todo = [sc for sc in scenarios if sc.name not in done]

    def finished(job, rows):
        for row in rows:
            results.append(row)
            if on_row:
                on_row(row)

    def failed(job, err):
        finished(job, [{"scenario": job[0].name, "seed": job[0].seed, **err}])

    run_tasks([(sc, str(out_dir), plot) for sc in todo], fn, workers=workers, on_rows=finished,
              on_failure=failed, scheduler=scheduler)
    latest = results.latest()
    return [latest[sc.name] for sc in scenarios if sc.name in latest], len(todo)
