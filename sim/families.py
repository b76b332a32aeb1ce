"""Scenario families after the paper's datasets, and the generator behind ``mapfusion scenarios generate``.

Each preset is a base scenario plus axes; :func:`family_toml` writes it as a family file
(DESIGN "Scenario files"), which ``mapfusion run`` and ``pytest scenarios/`` read.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import tomli_w

from mapfusion.errors import InputError


@dataclass(frozen=True)
class FamilyPreset:
    """A family: what it stands for, its base scenario, its axes and default maps and seeds."""

    description: str
    base: dict
    maps: tuple[str, ...]
    seeds: tuple[int, ...]
    odometry: tuple[str, ...] = ("vo",)
    weather: tuple[str, ...] = ("clear",)
    gps_mode: tuple[str, ...] = ("init_only",)
    claim: str = ""
    extra_axes: dict = field(default_factory=dict)


_DRIVE = {"duration_s": 480.0, "min_route_m": 1500.0}

#: Real data (shared/data/README.md), found through $MAPFUSION_DATA; runs are skipped where it is unset.
DATA = "${MAPFUSION_DATA}"
KITTI_SEQUENCES = ("00", "01", "02", "05", "07")

PRESETS: dict[str, FamilyPreset] = {
    "clear": FamilyPreset(
        "KITTI-like: clear weather, GPS at the start only",
        {**_DRIVE}, ("helsinki", "kotka"), (1, 2, 3), weather=("clear",),
        claim="Map-Fusion never worse than odometry by more than 0.3 m ATE in any run",
    ),
    "rain": FamilyPreset(
        "Oxford-like: rain, GPS at the start only",
        {**_DRIVE}, ("helsinki", "kotka"), (1, 2, 3), weather=("rain",),
        claim="mean ATE reduction of at least 40% against odometry",
    ),
    "rain-tunnel": FamilyPreset(
        "4Seasons-like: rain through GPS-denied, visually degraded zones and a real tunnel (Andorra: mountain roads, hairpins), GPS every 5 s outside them",
        {**_DRIVE, "gps": {"interval_s": 5.0}, "tunnels": [{"start_m": 600.0, "end_m": 900.0}],
         "route": {"via_tunnel": True}},
        ("tunnel", "helsinki", f"{DATA}/osm/andorra.osm.pbf"), (1, 2), weather=("rain",),
        odometry=("vo", "vio", "vo+wheel"), gps_mode=("interval",),
        claim="with wheel speed and gyro (vo+wheel): no run de-localised, every run has an estimate inside the "
              "GPS-denied zones, and their mean error there is at most 5 m",
    ),
    "heavy-rain": FamilyPreset(
        "Singapore-like: heavy rain, GPS every 5 s",
        {**_DRIVE, "gps": {"interval_s": 5.0}}, ("helsinki", "kotka"), (1, 2, 3), weather=("heavy_rain",),
        gps_mode=("interval",), claim="mean ATE reduction of at least 40% against odometry",
    ),
    "intersections": FamilyPreset(
        "Junctions: drives through the roundabout, y-split, parallel-road and grid maps, Helsinki, and the real Berlin Großer Stern and North Bayreuth motorway links, scored by match rate",
        {**_DRIVE, "min_route_m": 1200.0}, ("roundabout", "y-split", "parallel", "grid", "helsinki",
                                             f"{DATA}/osm/berlin-siegessaeule.osm.gz",
                                             f"{DATA}/osm/north-bayreuth.osm.gz"), (1, 2),
        claim="match rate at least 97%",
    ),
    "kidnapped": FamilyPreset(
        "Lost! (issue 17): after initialisation the estimate is knocked off — the initial fixes carry a 50–200 m "
        "bias, or the VO loses track for 8 s and re-initialises with a 30–300 m jump and up to 30° of heading "
        "error — and GPS never returns; the engine re-localises on the road network (map_relocalisation)",
        {"duration_s": 600.0, "min_route_m": 3000.0, "mapfusion": {"map_relocalisation": True}},
        ("helsinki", "kotka"), (1, 2, 3), weather=("clear",),
        claim="at least 90% of runs re-localised within 500 m of driving; mean online error after re-localisation "
              "at most 5 m",
        extra_axes={"kidnap.kind": ["gps_bias", "vo_jump"]},
    ),
    "kitti": FamilyPreset(
        "KITTI (paper Table I): the real drives with their real OSM, GPS from the RTK track for initialisation "
        "only, odometry synthesised on the real truth",
        {"duration_s": 86400.0, "gps": {"source": "recorded", "rate_hz": 10.0, "init_window_s": 30.0, "sigma_m": 0.5}},
        (), (1,), weather=("clear", "rain"), odometry=("vo", "vio"),
        extra_axes={"truth": [f"{DATA}/kitti/{n}" for n in KITTI_SEQUENCES]},
    ),
}


def family_dict(name: str, maps=None, seeds=None, weather=None, odometry=None, gps_mode=None,
                family_name: str | None = None) -> dict:
    """The family as a TOML-ready mapping; any argument left None takes the preset's value.
    ``seeds`` may be a count (1..N) or a list; ``family_name`` renames the family (and its runs)."""
    if name not in PRESETS:
        raise InputError(f"unknown family {name!r} (known: {', '.join(PRESETS)})")
    p = PRESETS[name]
    if isinstance(seeds, int):
        if seeds < 1:
            raise InputError(f"--seeds must be at least 1, got {seeds}")
        seeds = list(range(1, seeds + 1))
    axes = {k: list(v) for k, v in p.extra_axes.items()}
    if maps and not p.maps:
        raise InputError(f"family {name} takes its maps from its recorded drives; --maps does not apply")
    for key, given, default in (("map", maps, p.maps), ("weather.kind", weather, p.weather),
                                ("odometry.kind", odometry, p.odometry), ("gps.mode", gps_mode, p.gps_mode)):
        values = list(given) if given else list(default)
        if key == "map" and not p.maps:
            continue
        if not values:
            raise InputError(f"family {name}: no values for {key}")
        axes[key] = values
    base = copy.deepcopy(p.base)
    # single-valued axes go into the base so run names stay short
    for key in list(axes):
        if len(axes[key]) == 1 and key != "map":
            section, _, leaf = key.partition(".")
            base.setdefault(section, {})[leaf] = axes.pop(key)[0]
    fam = {"name": family_name or name, "seeds": list(seeds or p.seeds), "axes": axes}
    return {"family": fam, "base": base}


def family_toml(name: str, **kw) -> str:
    """A family file's text, with the preset's description and claim as comments."""
    d = family_dict(name, **kw)
    p = PRESETS[name]
    head = f"# {name}: {p.description}\n" + (f"# claim: {p.claim}\n" if p.claim else "")
    return head + tomli_w.dumps(d)
