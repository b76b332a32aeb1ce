"""Helpers of the harness tests that run SUMO (the engine's tests never import the harness or sim,
so these live here, not in tests/helpers.py)."""

from __future__ import annotations

from pathlib import Path


def simulated_grid_run(d: Path, name: str, seed: int, extra_toml: str = "") -> Path:
    """A 150 s SUMO drive on the bundled grid map with GPS throughout (so the engine initialises),
    simulated into ``d/run`` (``extra_toml`` adds tables); returns the run directory."""
    from mapfusion.harness.cli import main

    sc = d / f"{name}.toml"
    sc.write_text(f'name = "{name}"\nmap = "grid"\nseed = {seed}\nduration_s = 150.0\nmin_route_m = 1000.0\n'
                  '[gps]\nmode = "continuous"\n' + extra_toml)
    assert main(["simulate", str(sc), "--out", str(d / "run")]) == 0
    return d / "run"
