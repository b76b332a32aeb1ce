"""Reference pages generated from the code: ``docs/configuration.md`` from the field documentation
of :class:`~mapfusion.config.FusionConfig` and the scenario tables. ``python -m
mapfusion.harness.docs`` rewrites it; a test fails when the committed page is not current."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from mapfusion.config import FusionConfig, describe

PAGE = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"


def _cell(v) -> str:
    return str(v).replace("|", "\\|")


def _table(cls: type) -> list[str]:
    sources = {f.name: f.metadata.get("source", "") for f in dataclasses.fields(cls)}
    rows = ["| field | default | unit | meaning | source |", "|---|---|---|---|---|"]
    for name, _type, default, unit, doc in describe(cls):
        if dataclasses.is_dataclass(default) or isinstance(default, dict):
            continue  # a nested table, documented under its own heading
        rows.append(f"| `{name}` | {_cell(default)} | {_cell(unit)} | {_cell(doc)} | {_cell(sources[name])} |")
    return rows


def configuration_markdown() -> str:
    """The configuration reference page."""
    from sim.scenario import (EstimatorSpec, GpsConfig, ImuParams, KidnapConfig, RouteConfig, Scenario, TrafficConfig,
                              WeatherConfig)
    from sim.sensors import OdometryParams, WheelParams

    out = ["# Configuration reference", "",
           "Generated from the code's own field documentation by `python -m mapfusion.harness.docs`; a test",
           "fails when this page is not current. Every field has a default; a TOML table sets any of them,",
           "an unknown key or a value out of range is an error naming the key (a number with no stated",
           "maximum is still at most 10⁹ of its unit: `mapfusion.config.GENERIC_MAX`).", "",
           "## `[mapfusion]`: the engine (`FusionConfig`)", "",
           "The `[mapfusion]` table of a scenario file, `mapfusion fuse --config FILE`, `mapfusion sweep --variant",
           "NAME=FILE` and `--param NAME=...`. `FusionConfig.faithful()` is the paper's section III read directly.", "",
           "The engine's fixed values are not settings: each is named beside the code that uses it, with its unit and",
           "source — `mapfusion.relocalise.ParticleParams` (the road particles), `mapfusion.relocalise.SearchParams`",
           "(the map search), `mapfusion.tracking.RoadFixParams` (the road fixes) and module constants such as",
           "`mapfusion.track.OUTAGE_S`. A table that names a former setting is refused with one line giving its",
           "value and where it lives now (`FusionConfig.RETIRED_KEYS`).", ""]
    out += _table(FusionConfig)
    for title, cls in (("Scenario (top level)", Scenario), ("`[traffic]`", TrafficConfig), ("`[route]`", RouteConfig),
                       ("`[weather]`", WeatherConfig), ("`[gps]`", GpsConfig), ("`[imu]`", ImuParams),
                       ("`[odometry]`: the preset fields a scenario may replace", OdometryParams),
                       ("`[wheel]`: the wheel-speed sensor of odometry kinds vo+wheel and vio+wheel (`vehicle = "
                        "\"car\" | \"truck\"` picks the preset; any field below replaces the preset's; the gyro is "
                        "the `[imu]`'s)", WheelParams),
                       ("`[kidnap]`: the estimate knocked off after initialisation (issue 17; the `kidnapped` "
                        "family)", KidnapConfig),
                       ("`[[estimators]]`: methods scored beside the odometry and Map-Fusion (one table each; "
                        "docs/commands.md, \"Your own method\")", EstimatorSpec)):
        out += ["", f"## {title}", ""] + _table(cls)
    return "\n".join(out) + "\n"


def main() -> None:
    PAGE.write_text(configuration_markdown())
    print(f"wrote {PAGE}", file=sys.stderr)


if __name__ == "__main__":
    main()
