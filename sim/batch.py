"""Many scenarios at once, in worker processes (libsumo runs one simulation per process)."""

from __future__ import annotations

import multiprocessing as mp
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from .scenario import Scenario


def _one(sc: Scenario, out_dir: str | None, plot: bool) -> dict:
    from mapfusion.errors import InputError

    from .run import run_scenario

    try:
        return run_scenario(sc, None if out_dir is None else Path(out_dir) / sc.name, plot=plot).metrics
    except InputError as exc:
        return {"scenario": sc.name, "seed": sc.seed, "error": str(exc)}
    except Exception as exc:  # a failed run never costs the others their results
        return {"scenario": sc.name, "seed": sc.seed, "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(limit=5)}


def run_many(scenarios: list[Scenario], workers: int = 2, out_dir: str | Path | None = None, plot: bool = False,
             on_result=None) -> list[dict]:
    """Metrics of every scenario, in the given order; ``on_result(metrics)`` as each finishes."""
    if workers <= 1:
        results = []
        for sc in scenarios:
            r = _one(sc, None if out_dir is None else str(out_dir), plot)
            results.append(r)
            if on_result:
                on_result(r)
        return results
    by_name: dict[str, dict] = {}
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork")) as pool:
        futures = {pool.submit(_one, sc, None if out_dir is None else str(out_dir), plot): sc for sc in scenarios}
        for fut in as_completed(futures):
            sc = futures[fut]
            try:
                r = fut.result()
            except Exception as exc:  # the worker process died
                r = {"scenario": sc.name, "seed": sc.seed, "error": f"worker died: {exc}"}
            by_name[sc.name] = r
            if on_result:
                on_result(r)
    return [by_name[sc.name] for sc in scenarios]
