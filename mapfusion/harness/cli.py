"""The ``mapfusion`` command line (typer + rich).

The CLI owns printing, progress and exit codes: bad input exits 2 with one line on stderr, an
internal failure exits 1. Heavy modules are imported inside the commands so ``--help`` is quick.
"""

from __future__ import annotations

import inspect
import json
import math
import os

import numpy as np
import logging
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from .errors import InputError

app = typer.Typer(
    name="mapfusion",
    help="Map-Fusion test bed: simulate drives on OSM maps, fuse odometry, GPS and the map, score against truth.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
maps_app = typer.Typer(help="Road maps: build, inspect and generate.", no_args_is_help=True)
app.add_typer(maps_app, name="maps")
scenarios_app = typer.Typer(help="Scenario families.", no_args_is_help=True)
app.add_typer(scenarios_app, name="scenarios")
import_app = typer.Typer(help="Recorded datasets in the project's formats.", no_args_is_help=True)
app.add_typer(import_app, name="import")

console = Console()
err_console = Console(stderr=True)


def _fail(message: str, code: int = 2) -> None:
    """One clear line on stderr and the exit code (2: bad input)."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="More log output (-v info, -vv debug).")] = 0,
) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    from rich.logging import RichHandler

    logging.basicConfig(level=level, handlers=[RichHandler(console=err_console, show_path=False)], force=True)


def _stats_table(stats, title: str) -> Table:
    t = Table(title=title, show_header=True)
    t.add_column("quantity")
    t.add_column("value", justify="right")
    rows = [
        ("OSM ways (drivable)", f"{stats.ways:,}"),
        ("graph edges", f"{stats.edges:,}"),
        ("junctions (degree ≥ 3)", f"{stats.junctions:,}"),
        ("graph vertices", f"{stats.vertices:,}"),
        ("way-points", f"{stats.waypoints:,}"),
        ("road length", f"{stats.road_km:.2f} km"),
        ("tunnel length", f"{stats.tunnel_km:.2f} km"),
        ("mean way-point spacing", f"{stats.mean_spacing_m:.3f} m"),
        ("build time", f"{stats.build_s:.2f} s" + (" (read from cache)" if stats.from_cache else "")),
    ]
    for k, v in rows:
        t.add_row(k, v)
    return t


@maps_app.command("build")
def maps_build(
    osm: Annotated[str, typer.Argument(help="OSM file (.osm, .osm.gz, .osm.bz2, .osm.pbf) or a built-in map name.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the statistics as JSON.")] = False,
    spacing_m: Annotated[float, typer.Option(help="Way-point spacing in metres.")] = 1.0,
    lane_width_m: Annotated[float, typer.Option(help="Lane width in metres (road width = lanes × lane width).")] = 3.0,
    no_cache: Annotated[bool, typer.Option("--no-cache", help="Rebuild even when a cached map exists.")] = False,
) -> None:
    """Build the processed road map of an OSM file (cached) and print its statistics."""
    from .maps import resolve_map
    from .roadmap import RoadMap, RoadMapConfig

    try:
        cfg = RoadMapConfig(spacing_m=spacing_m, lane_width_m=lane_width_m)
        path = resolve_map(osm)
        with err_console.status(f"building road map of {path.name} ..."):
            road = RoadMap.from_osm(path, cfg, cache=not no_cache)
    except InputError as exc:
        _fail(str(exc))
    stats = road.stats()
    if as_json:
        print(json.dumps(stats.to_dict(), indent=2))
    else:
        console.print(_stats_table(stats, f"Road map: {path}"))


def _parse_params(pairs: list[str], func) -> dict:
    """``KEY=VALUE`` pairs → keyword arguments of ``func``, converted to its parameters' types."""
    sig = inspect.signature(func)
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise InputError(f"--param {pair!r}: expected KEY=VALUE")
        key, value = (s.strip() for s in pair.split("=", 1))
        if key not in sig.parameters:
            raise InputError(f"--param {key!r}: {func.__name__} takes {', '.join(sig.parameters) or 'no parameters'}")
        default = sig.parameters[key].default
        try:
            out[key] = type(default)(value) if default is not inspect.Parameter.empty else float(value)
        except ValueError as exc:
            raise InputError(f"--param {key}={value!r}: not a {type(default).__name__}") from exc
    return out


@maps_app.command("generate")
def maps_generate(
    kind: Annotated[str, typer.Argument(help="grid | roundabout | y-split | parallel | tunnel | city")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output OSM XML file.")],
    param: Annotated[
        Optional[list[str]],
        typer.Option(
            "--param",
            "-p",
            help="Generator parameter KEY=VALUE, repeatable. grid: cols, rows, block_m; roundabout: radius_m, arm_m; "
            "parallel: offset_m (6–10), length_m; tunnel: tunnel_m (≥ 600), bend_deg, bend_radius_m; "
            "city: width_km (≤ 10), height_km (≤ 15), block_m, arterial_every.",
        ),
    ] = None,
) -> None:
    """Write a synthetic OSM map (valid OSM XML with real highway, lanes, oneway, tunnel, bridge, layer tags)."""
    from . import synthetic

    try:
        k = synthetic.SyntheticKind(kind)
    except ValueError:
        _fail(f"unknown map kind {kind!r}; known: {', '.join(x.value for x in synthetic.SyntheticKind)}")
    try:
        params = _parse_params(param or [], synthetic._GENERATORS[k])
        path = synthetic.write(k, out, **params)
    except InputError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"{out}: cannot write ({exc.strerror})")
    console.print(f"wrote {k.value} map to {path} ({path.stat().st_size:,} bytes)")


@maps_app.command("stress")
def maps_stress(
    osm: Annotated[str, typer.Argument(help="OSM file or built-in map name.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
    offset_extra_m: Annotated[float, typer.Option(help="Across-road offsets reach ±(road width + this), metres.", min=0.0)] = 3.0,
    heading_error_deg: Annotated[float, typer.Option(help="Heading errors uniform in ± this, degrees.", min=0.0)] = 20.0,
    poses_per_station: Annotated[int, typer.Option(help="Random poses per station and direction.", min=1)] = 4,
    radius_m: Annotated[float, typer.Option(help="Matcher search radius, metres.")] = 20.0,
    angle_weight: Annotated[float, typer.Option("--angle-weight-m-per-deg", help="w in D = E + w·A, metres per degree.", min=0.0)] = 1.0,
    lane_width_m: Annotated[float, typer.Option(help="Lane width, metres (road width = lanes × lane width).")] = 3.0,
    seed: Annotated[int, typer.Option(help="Seed of offsets and heading errors.")] = 0,
) -> None:
    """Stress-test the road matcher around every junction; match rate overall and by junction kind."""
    from .maps import resolve_map
    from .roadmap import RoadMap, RoadMapConfig
    from .stress import StressConfig, run_stress

    try:
        cfg = StressConfig(
            offset_extra_m=offset_extra_m,
            heading_error_deg=heading_error_deg,
            poses_per_station=poses_per_station,
            radius_m=radius_m,
            angle_weight_m_per_deg=angle_weight,
            seed=seed,
        )
        path = resolve_map(osm)
        with err_console.status(f"matching poses around the junctions of {path.name} ..."):
            road = RoadMap.from_osm(path, RoadMapConfig(lane_width_m=lane_width_m))
            result = run_stress(road, cfg)
    except InputError as exc:
        _fail(str(exc))
    if as_json:
        print(json.dumps(result.to_dict(), indent=2))
        return
    t = Table(title=f"Matcher stress test: {path.name}")
    for col in ("junction kind", "junctions", "poses", "matched to their way"):
        t.add_column(col, justify="right")
    for k in result.by_kind:
        t.add_row(k.kind, str(k.junctions), f"{k.poses:,}", f"{100 * k.rate:.1f} %")
    t.add_row("all", str(result.junctions), f"{result.poses:,}", f"{100 * result.rate:.1f} %" if result.poses else "–", style="bold")
    console.print(t)
    console.print(
        f"offsets up to road width + {offset_extra_m:g} m, heading errors up to ±{heading_error_deg:g}°, "
        f"D = E + {angle_weight:g}·A within {radius_m:g} m; {result.unmatched_none} poses had no way-point in range"
    )


@scenarios_app.command("generate")
def scenarios_generate(
    family: Annotated[str, typer.Option("--family", help="clear | rain | rain-tunnel | heavy-rain | intersections | kitti")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Family file to write (TOML).")],
    maps: Annotated[Optional[list[str]], typer.Option("--maps", help="Maps (built-in names or OSM paths), repeatable.")] = None,
    seeds: Annotated[Optional[int], typer.Option("--seeds", help="Seeds 1..N.", min=1)] = None,
    weather: Annotated[Optional[list[str]], typer.Option("--weather", help="clear | rain | heavy_rain, repeatable.")] = None,
    odometry: Annotated[Optional[list[str]], typer.Option("--odometry", help="vo | vio, repeatable.")] = None,
    gps_mode: Annotated[Optional[list[str]], typer.Option("--gps-mode", help="init_only | interval | continuous, repeatable.")] = None,
    name: Annotated[Optional[str], typer.Option("--name", help="Name of the family (and prefix of its runs).")] = None,
) -> None:
    """Write a scenario family after one of the paper's datasets (any axis can be overridden)."""
    from sim.families import family_toml
    from sim.scenario import expand_family

    try:
        text = family_toml(family, maps=maps, seeds=seeds, weather=weather, odometry=odometry, gps_mode=gps_mode,
                           family_name=name)
        import tomllib

        fam = expand_family(tomllib.loads(text), str(out), Path.cwd())  # validates every run now
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    except InputError as exc:
        _fail(str(exc))
    console.print(f"wrote family {family} ({len(fam.scenarios) + len(fam.unavailable)} runs) to {out}")
    if fam.unavailable:
        err_console.print(f"[yellow]{len(fam.unavailable)} of them cannot run here:[/] {fam.unavailable[0][1]}", highlight=False)


@import_app.command("kitti")
def import_kitti_cmd(
    poses: Annotated[Path, typer.Option("--poses", help="KITTI poses.txt (12 numbers a line, camera 0).")],
    times: Annotated[Path, typer.Option("--times", help="KITTI times.txt.")],
    gps: Annotated[Path, typer.Option("--gps", help="RTK track as a KML LineString, one point per frame.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")],
    map_path: Annotated[Optional[str], typer.Option("--map", help="OSM map defining the ENU frame "
                                                    "(default: map.osm beside the poses).")] = None,
    gps_at: Annotated[str, typer.Option("--gps-at", help="camera: the fixes moved to camera 0 by the fitted lever arm "
                                        "(what a camera odometry is compared with); antenna: the raw track.")] = "camera",
) -> None:
    """A KITTI sequence as a run directory: truth.tum in the map's ENU frame (georeferenced to the RTK
    track with the antenna's lever arm), gps.csv from the track, import.json with the fit's residual."""
    from .kitti import import_kitti, write_import
    from .maps import resolve_map
    from .roadmap import RoadMap

    try:
        mp = resolve_map(map_path) if map_path else resolve_map(poses.parent / "map.osm")
        road = RoadMap.from_osm(mp)
        if gps_at not in ("camera", "antenna"):
            raise InputError(f"--gps-at is camera or antenna, got {gps_at!r}")
        imp = import_kitti(poses, times, gps, road.projection)
        write_import(out, imp, road.projection, str(Path(mp).resolve()), gps_at_camera=gps_at == "camera")
    except InputError as exc:
        _fail(str(exc))
    g = imp.georef
    console.print(f"{len(imp.t_s):,} frames → {out}; fit residual {g.residual_rmse_m:.3f} m RMSE "
                  f"(max {g.residuals_m.max():.2f} m, {int(imp.filled.sum())} filled track points left out); lever arm (camera x right, y down, z forward) "
                  f"{g.lever_arm_cam_m[0]:+.2f}, {g.lever_arm_cam_m[1]:+.2f}, {g.lever_arm_cam_m[2]:+.2f} m")


@app.command()
def simulate(
    scenario: Annotated[Path, typer.Argument(help="Scenario TOML file (DESIGN 'Scenario files').")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")],
    truth: Annotated[Optional[Path], typer.Option("--truth", help="A recorded truth (TUM, in the scenario map's ENU "
                                                  "frame, e.g. RUN/truth.tum of mapfusion import kitti): the sensors "
                                                  "are synthesised on it instead of a SUMO drive.")] = None,
) -> None:
    """Drive the scenario in SUMO (or take a recorded --truth), synthesise the sensors and write the run
    directory: scenario.toml (resolved), truth.tum, truth.csv, odometry.tum, gps.csv, imu.csv (and fleet.csv
    in fleet mode)."""
    # The engine never needs SUMO: the simulation is imported only by the commands that drive it.
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from sim.drive import run_drive
    from sim.network import RouteError, SimulationError, build_network
    from sim.rundir import write_sensors, write_truth
    from sim.scenario import load_scenario
    from sim.sensors import Truth, synthesise, under_bridges

    from .roadmap import RoadMap

    try:
        sc = load_scenario(scenario)
    except InputError as exc:
        _fail(str(exc))
    if truth is not None or sc.truth:
        from sim.rundir import write_recorded_truth
        from sim.run import simulate_scenario

        try:
            if truth is not None:
                if not truth.exists():
                    raise InputError(f"{truth}: no such file or directory")
                sc = sc.replace(truth=str(truth.resolve()))
            src = sc.truth
            sim = simulate_scenario(sc)  # a recorded drive: no SUMO
            rec, sensors = sim.truth, sim.sensors
            write_recorded_truth(out, sc, rec.t_s, np.column_stack([rec.x_m, rec.y_m, rec.z_m]), rec.yaw_rad,
                                 rec.visually_degraded, sim.road.projection)
            write_sensors(out, sensors, sim.road.projection)
        except InputError as exc:
            _fail(str(exc))
        console.print(f"{sc.name}: sensors on the recorded truth {src} ({len(rec):,} frames): "
                      f"{len(sensors.odometry.t_s):,} odometry frames, {len(sensors.gps.t_s)} GPS fixes → {out}")
        return
    try:
        with err_console.status("building road map and SUMO network ..."):
            road = RoadMap.from_osm(sc.map)
            net = build_network(sc.map)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
                      TimeElapsedColumn(), console=err_console, transient=True, disable=not err_console.is_terminal) as bar:
            task = bar.add_task(f"simulating {sc.name}", total=sc.duration_s)
            drive = run_drive(sc, road, net, progress=lambda t, total: bar.update(task, completed=t))
        with err_console.status("synthesising odometry, IMU and GPS ..."):
            bridges = under_bridges(road, drive.ego.x_m, drive.ego.y_m, drive.ego.osm_way)
            sensors = synthesise(sc, Truth.from_track(drive.ego, bridges, sc.gps))
        write_truth(out, sc, drive)
        write_sensors(out, sensors, road.projection)
    except RouteError as exc:
        _fail(f"{scenario}: {exc}")
    except InputError as exc:
        _fail(str(exc))
    except SimulationError as exc:
        _fail(f"{scenario}: {exc}", code=1)
    console.print(
        f"{sc.name}: {len(drive.ego):,} frames, {drive.ego.t_s[-1]:.1f} s simulated, {drive.ego.distance_m[-1]:,.0f} m driven "
        f"(route {drive.route_length_m:,.0f} m), {drive.realtime_factor:,.0f}× real time; "
        f"{len(sensors.odometry.t_s):,} odometry frames, {len(sensors.gps.t_s)} GPS fixes → {out}"
    )


@app.command()
def fuse(
    map_path: Annotated[str, typer.Option("--map", help="OSM file or built-in map name.")],
    odometry: Annotated[Path, typer.Option("--odometry", help="Odometry poses in its own frame (TUM, or KITTI with --times).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Estimate to write (TUM, map ENU frame).")],
    gps: Annotated[Optional[Path], typer.Option("--gps", help="GPS CSV (t,lat,lon,alt,sigma_m).")] = None,
    imu: Annotated[Optional[Path], typer.Option("--imu", help="IMU CSV (t,ax,ay,az,gx,gy,gz); read and checked. "
                                                "The engine does not use it: VIO users pass their VIO's poses.")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="TOML with a [mapfusion] table (FusionConfig).")] = None,
    odometry_format: Annotated[str, typer.Option("--odometry-format", help="tum | kitti")] = "tum",
    times: Annotated[Optional[Path], typer.Option("--times", help="Timestamps, one a line (KITTI times.txt).")] = None,
    odometry_frame: Annotated[str, typer.Option("--odometry-frame", help="body (x fwd, y left, z up) | camera (x right, y down, z fwd)")] = "body",
    no_map: Annotated[bool, typer.Option("--no-map", help="The baseline: same GPS use, no map priors.")] = False,
    smoothed: Annotated[Optional[Path], typer.Option("--smoothed", help="Also write the smoothed trajectory (TUM).")] = None,
    gps_until_s: Annotated[Optional[float], typer.Option("--gps-until-s", help="Use GPS fixes only this many seconds "
                                                         "from the first odometry frame (the paper's KITTI protocol: "
                                                         "GPS for initialisation only).", min=0.0)] = None,
) -> None:
    """Run the engine on recorded odometry and GPS with an OSM map; write the online (causal) estimate."""
    from .formats import FormatError, read_gps_csv, read_imu_csv, write_tum
    from .maps import resolve_map
    from .roadmap import RoadMap
    from .runner import OdometryFormat, OdometryFrame, fuse as run_fuse, load_fusion_config, poses_to_arrays, read_odometry

    try:
        try:
            fmt = OdometryFormat(odometry_format)
            frame = OdometryFrame(odometry_frame)
        except ValueError as exc:
            raise InputError(f"{exc}; --odometry-format is tum or kitti, --odometry-frame is body or camera") from None
        cfg = load_fusion_config(config, **({"use_map": False} if no_map else {}))
        t_odo, poses = read_odometry(odometry, fmt, times, frame)
        fixes = read_gps_csv(gps) if gps is not None else None
        if fixes is not None and gps_until_s is not None:
            from .formats import GpsFixes

            keep = fixes.t_s <= t_odo[0] + gps_until_s
            fixes = GpsFixes(fixes.t_s[keep], fixes.lat_deg[keep], fixes.lon_deg[keep], fixes.alt_m[keep], fixes.sigma_m[keep])
        if imu is not None:
            read_imu_csv(imu)
        with err_console.status("building road map ..."):
            road = RoadMap.from_osm(resolve_map(map_path), RoadMapConfig_for(cfg))
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn("[bold]fusing"), BarColumn(), TextColumn("{task.completed:,}/{task.total:,} frames"),
                      TimeElapsedColumn(), console=err_console, transient=True, disable=not err_console.is_terminal) as bar:
            task = bar.add_task("fuse", total=len(t_odo))
            res = run_fuse(road, t_odo, poses, fixes, cfg, progress=lambda k, n: bar.update(task, completed=k))
    except FormatError as exc:
        _fail(str(exc))
    except InputError as exc:
        _fail(str(exc))
    eng = res.engine
    if not eng.initialised:
        _fail("the engine never initialised: it needs GPS fixes while the vehicle moves "
              f"(got {eng.counters.gps_before_init} fixes, {len(eng._scale_est.samples)} scale samples)")
    idx = [i for i, p in enumerate(res.online) if p is not None]
    xyz, q = poses_to_arrays([res.online[i] for i in idx])
    write_tum(out, res.t_s[idx], xyz, q, header=f"Map-Fusion online estimate ({'no map' if no_map else 'with map'})")
    if smoothed is not None:
        ts = sorted(res.smoothed)
        sxyz, sq = poses_to_arrays([res.smoothed[t] for t in ts])
        write_tum(smoothed, np.asarray(ts), sxyz, sq, header="Map-Fusion smoothed trajectory")
    c = eng.counters
    console.print(f"{len(idx):,} poses → {out}; scale {eng.scale:.4f} ± {eng.scale_sigma or 0:.4f}, "
                  f"initialised at t = {eng.initialised_at:.1f} s; map priors {c.map_priors}, GPS used {c.gps_used} "
                  f"(rejected {c.gps_rejected_gate + c.gps_rejected_invalid}), odometry priors {c.odometry_priors}, "
                  f"recoveries {c.recoveries}")


def RoadMapConfig_for(cfg):  # noqa: N802 - a small factory kept next to its one user
    """The road map with the engine's lane width."""
    from .roadmap import RoadMapConfig

    return RoadMapConfig(lane_width_m=cfg.lane_width_m)


@app.command()
def evaluate(
    truth: Annotated[Path, typer.Option("--truth", help="Ground truth (TUM).")],
    estimate: Annotated[Path, typer.Option("--estimate", help="Estimate (TUM), e.g. from mapfusion fuse.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON.")] = False,
    max_dt_s: Annotated[float, typer.Option(help="Poses match when their times differ by at most this, seconds.")] = 0.02,
    delocalization_m: Annotated[float, typer.Option(help="ATE above this counts as de-localised, metres.")] = 20.0,
) -> None:
    """ATE (the paper's), online error (no alignment; lateral and longitudinal parts) and RPE per 100 m."""
    from .formats import FormatError, quaternion_to_yaw, read_tum
    from .metrics import ate, associate, delocalized, online_error, rpe_per_100m

    try:
        tt, xt, qt = read_tum(truth)
        te, xe, qe = read_tum(estimate)
        ia, ib = associate(te, tt, max_dt_s)
        if len(ia) < 3:
            raise InputError(f"{estimate}: only {len(ia)} poses match {truth} in time (within {max_dt_s} s)")
        a = ate(xt[ib], xe[ia])
        yt, ye = quaternion_to_yaw(qt[ib]), quaternion_to_yaw(qe[ia])
        on = online_error(xt[ib], yt, xe[ia])
        rpe = rpe_per_100m(xt[ib], yt, xe[ia], ye)
    except (FormatError, InputError) as exc:
        _fail(str(exc))
    out = {"frames": int(len(ia)), "ate_m": a, "delocalized": delocalized(a, delocalization_m),
           "online_rmse_m": on.rmse_m, "online_max_m": on.max_m, "online_lateral_rmse_m": on.lateral_rmse_m,
           "online_longitudinal_rmse_m": on.longitudinal_rmse_m, "rpe_per_100m_m": rpe}
    if as_json:
        print(json.dumps(out, indent=2))
        return
    t = Table(title=f"{estimate.name} against {truth.name}")
    t.add_column("metric")
    t.add_column("value", justify="right")
    for k, v in out.items():
        t.add_row(k, "–" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v)))
    console.print(t)


def _paper_table(rows: list[dict], title: str, strip_prefix: str = "", width: int | None = None) -> Table:
    """Runs as columns, rows odometry / + Map-Fusion / reduction (ATE, m); x = de-localised; the
    average leaves the de-localised runs out, as the paper's tables do. When the columns would not
    fit in ``width`` characters, the same table turned: a row per run, then Avg."""
    ok = [r for r in rows if "ate_odometry_m" in r]
    names = [r["scenario"].removeprefix(strip_prefix) for r in rows]

    def cell(r, key, flag):
        if "ate_odometry_m" not in r:
            return "failed"
        return "x" if r[flag] else f"{r[key]:.2f}"

    def reduction(r):
        if "ate_odometry_m" not in r or r["delocalized_odometry"] or r["delocalized_mapfusion"]:
            return "NA"
        return f"{r['ate_reduction_m']:.2f}"

    kept_o = [r["ate_odometry_m"] for r in ok if not r["delocalized_odometry"]]
    kept_m = [r["ate_mapfusion_m"] for r in ok if not r["delocalized_mapfusion"]]
    avg = lambda v: f"{sum(v) / len(v):.2f}" if v else "–"  # noqa: E731
    both = [r for r in ok if not r["delocalized_odometry"] and not r["delocalized_mapfusion"]]
    averages = (avg(kept_o), avg(kept_m), avg([r["ate_reduction_m"] for r in both]))
    t = Table(title=title, show_lines=False)
    needed = len("+ Map-Fusion") + sum(max(len(n), 7) + 3 for n in names) + 10
    if width is not None and needed > width:
        t.add_column("run", no_wrap=True)
        for c in ("odometry", "+ Map-Fusion", "reduction"):
            t.add_column(c, justify="right")
        for n, r in zip(names, rows):
            t.add_row(n, cell(r, "ate_odometry_m", "delocalized_odometry"),
                      cell(r, "ate_mapfusion_m", "delocalized_mapfusion"), reduction(r))
        t.add_row("Avg", *averages, style="bold")
        return t
    t.add_column("ATE (m)", no_wrap=True)
    for n in names:
        t.add_column(n, justify="right")
    t.add_column("Avg", justify="right", style="bold")
    t.add_row("odometry", *[cell(r, "ate_odometry_m", "delocalized_odometry") for r in rows], averages[0])
    t.add_row("+ Map-Fusion", *[cell(r, "ate_mapfusion_m", "delocalized_mapfusion") for r in rows], averages[1])
    t.add_row("reduction", *[reduction(r) for r in rows], averages[2], style="italic")
    return t


def _table_one(rows: list[dict], title: str) -> Table:
    """The paper's Table I layout for recorded drives: sequences as columns, for each odometry kind ×
    weather the rows odometry / + Map-Fusion / reduction (ATE, m). A cell over several seeds is their
    mean; x = every seed de-localised; Avg leaves de-localised cells out, as the paper does."""
    import numpy as np

    ok = [r for r in rows if "ate_odometry_m" in r]
    seq = lambda r: Path(r.get("recorded", r["scenario"])).name  # noqa: E731
    columns = sorted({seq(r) for r in rows})
    groups = sorted({(r.get("odometry", "?"), r.get("weather", "?")) for r in rows})
    t = Table(title=title, show_lines=False)
    t.add_column("ATE (m)", no_wrap=True)
    for c in columns:
        t.add_column(c, justify="right")
    t.add_column("Avg", justify="right", style="bold")

    def cell(runs, key, flag):
        kept = [r[key] for r in runs if not r[flag]]
        return float(np.mean(kept)) if kept else None

    for odo, weather in groups:
        cells_o, cells_m = [], []
        for c in columns:
            runs = [r for r in ok if seq(r) == c and (r["odometry"], r["weather"]) == (odo, weather)]
            failed = any(seq(r) == c and (r.get("odometry"), r.get("weather")) == (odo, weather) and "error" in r
                         for r in rows)
            cells_o.append("failed" if failed and not runs else cell(runs, "ate_odometry_m", "delocalized_odometry") if runs else "")
            cells_m.append("failed" if failed and not runs else cell(runs, "ate_mapfusion_m", "delocalized_mapfusion") if runs else "")
        fmt = lambda v: v if isinstance(v, str) else ("x" if v is None else f"{v:.2f}")  # noqa: E731
        num = lambda vs: [v for v in vs if isinstance(v, float)]  # noqa: E731
        both = [(a, b) for a, b in zip(cells_o, cells_m) if isinstance(a, float) and isinstance(b, float)]
        avg = lambda v: f"{sum(v) / len(v):.2f}" if v else "–"  # noqa: E731
        label = f"{odo.upper()} {weather.replace('_', ' ')}"
        t.add_row(label, *[fmt(v) for v in cells_o], avg(num(cells_o)))
        t.add_row(f"{label} + Map-Fusion", *[fmt(v) for v in cells_m], avg(num(cells_m)))
        red = [f"{a - b:.2f}" if isinstance(a, float) and isinstance(b, float) else "NA" for a, b in zip(cells_o, cells_m)]
        t.add_row("reduction", *red, avg([a - b for a, b in both]), style="italic", end_section=True)
    return t


def _default_workers() -> int:
    return max(1, os.cpu_count() or 1)


def _load_runs(paths: list[Path]):
    """Scenarios of every file, the unavailable ones reported and left out; exit 2 on bad input."""
    from sim.scenario import load_family

    try:
        families = [load_family(p) for p in paths]
    except InputError as exc:
        _fail(str(exc))
    scenarios = [sc for fam in families for sc in fam.scenarios]
    skipped = [(name, why) for fam in families for name, why in fam.unavailable]
    for name, why in skipped:
        err_console.print(f"[yellow]skipped {name}:[/] {why}", highlight=False)
    if not scenarios:
        _fail(f"no run can be made here: {skipped[0][1]}" if skipped else "no runs")
    names = [sc.name for sc in scenarios]
    if len(set(names)) != len(names):
        _fail("two runs share a name: " + ", ".join(sorted({n for n in names if names.count(n) > 1})))
    return scenarios


class _RunBar:
    """A progress bar of runs done, failed and remaining (silent off a terminal)."""

    def __init__(self, total: int, label: str = "runs") -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.done = self.failed = 0
        self.total = total
        self.bar = Progress(TextColumn(f"[bold]{label}"), BarColumn(),
                            TextColumn("{task.fields[done]} done, [red]{task.fields[failed]} failed[/], "
                                       "{task.fields[left]} remaining"),
                            TimeElapsedColumn(), TimeRemainingColumn(), console=err_console,
                            disable=not err_console.is_terminal)
        self.task = self.bar.add_task(label, total=total, done=0, failed=0, left=total)

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        self.bar.__exit__(*exc)

    def advance(self, failed: bool) -> None:
        self.done += not failed
        self.failed += failed
        self.bar.update(self.task, advance=1, done=self.done, failed=self.failed,
                        left=self.total - self.done - self.failed)


@app.command()
def run(
    paths: Annotated[list[Path], typer.Argument(help="Scenario or family TOML files.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory for the run directories and results.jsonl.")],
    workers: Annotated[Optional[int], typer.Option("--workers", "-j", min=1,
                                                   help="Runs at a time, each in its own process (default: the CPU count).")] = None,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="A Dask scheduler (tcp://HOST:PORT): the runs go to "
                                                     "its workers instead of local processes.")] = None,
    no_plot: Annotated[bool, typer.Option("--no-plot", help="Skip plot.png in each run directory.")] = False,
) -> None:
    """Each scenario (or every run of a family): simulate, baseline and Map-Fusion, evaluate; one run
    directory each, results.jsonl (a line per finished run, appended at once), and the paper-style
    table. Runs already in results.jsonl without error are skipped: the same command resumes."""
    from sim.batch import ResultsLog, run_logged

    scenarios = _load_runs(paths)
    out.mkdir(parents=True, exist_ok=True)
    done = ResultsLog(out / "results.jsonl").done()
    left = sum(sc.name not in done for sc in scenarios)
    if left < len(scenarios):
        err_console.print(f"resuming: {len(scenarios) - left} of {len(scenarios)} runs already in {out / 'results.jsonl'}")
    with _RunBar(left) as bar:
        rows, _ = run_logged(scenarios, out, workers=workers or _default_workers(), plot=not no_plot,
                             scheduler=scheduler, on_row=lambda row: bar.advance("error" in row))
    console.print(_paper_table(rows, f"ATE over {len(rows)} run(s) → {out}", width=console.width))
    failed_rows = [r for r in rows if "error" in r]
    for r in failed_rows:
        err_console.print(f"[red]{r['scenario']} failed:[/] {r['error']}", highlight=False)
    if failed_rows and len(failed_rows) == len(rows):
        raise typer.Exit(1)


@app.command()
def sweep(
    paths: Annotated[list[Path], typer.Argument(help="Scenario or family TOML files.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory for results.jsonl and sweep_heatmap.png.")],
    param: Annotated[Optional[list[str]], typer.Option("--param", "-p", help="NAME=V1,V2,... over a FusionConfig field, "
                                                       "repeatable: the grid is their product.")] = None,
    variant: Annotated[Optional[list[str]], typer.Option("--variant", "-V", help="A named engine configuration, repeatable: "
                                                         "'defaults', 'faithful' (the paper's section III read directly) "
                                                         "or NAME=FILE.toml (a [mapfusion] table of overrides); "
                                                         "crossed with the --param grid.")] = None,
    workers: Annotated[Optional[int], typer.Option("--workers", "-j", min=1, help="Scenarios at a time (default: the CPU count).")] = None,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="A Dask scheduler (tcp://HOST:PORT).")] = None,
) -> None:
    """A grid over engine parameters and named configurations: every scenario is simulated once and
    fused at every grid point. results.jsonl gets a line per (run, grid point), with `params` (a
    variant's name under `variant`); the same command resumes. Writes a heatmap of the mean
    Map-Fusion ATE and prints the grid."""
    from sim.batch import ResultsLog, run_tasks
    from sim.sweep import grid_points, mean_ate_table, parse_grid, parse_variants, plot_heatmap, row_key, sweep_task

    try:
        if not param and not variant:
            raise InputError("give at least one --param NAME=V1,V2,... or --variant")
        variants = parse_variants(variant or [])
        grid = {"variant": list(variants)} if variants else {}
        if param:
            grid.update(parse_grid(param))
    except InputError as exc:
        _fail(str(exc))
    scenarios = _load_runs(paths)
    out.mkdir(parents=True, exist_ok=True)
    results = ResultsLog(out / "results.jsonl")
    done = results.done(row_key)
    points = grid_points(grid)
    jobs = []
    for sc in scenarios:
        todo = [p for p in points if row_key({"scenario": sc.name, "params": p}) not in done]
        if todo:
            jobs.append((sc, todo, variants))
    left = sum(len(j[1]) for j in jobs)
    if left < len(scenarios) * len(points):
        err_console.print(f"resuming: {len(scenarios) * len(points) - left} of {len(scenarios) * len(points)} "
                          f"fusions already in {results.path}")
    sims = 0
    with _RunBar(left, "fusions") as bar:
        def finished(job, rows):
            nonlocal sims
            for row in rows:
                sims += bool(row.get("simulated"))
                results.append(row)
                bar.advance("error" in row)

        def failed(job, err):
            finished(job, [{"scenario": job[0].name, "seed": job[0].seed, "params": p, **err} for p in job[1]])

        run_tasks(jobs, sweep_task, workers=workers or _default_workers(), on_rows=finished, on_failure=failed,
                  scheduler=scheduler)
    names = {sc.name for sc in scenarios}
    rows = [r for r in results.latest(row_key).values() if r.get("scenario") in names]
    table = mean_ate_table(rows, grid)
    t = Table(title=f"mean ATE (m) over {len(scenarios)} run(s) per grid point")
    for k in grid:
        t.add_column(k, justify="right")
    for c in ("runs", "failed", "odometry", "+ Map-Fusion", "de-localised"):
        t.add_column(c, justify="right")
    for v in table.values():
        t.add_row(*[str(v["params"][k]) for k in grid], str(v["runs"]), str(v["failed"]), f"{v['ate_odometry_m']:.2f}",
                  f"{v['ate_mapfusion_m']:.2f}", str(v["delocalized"]))
    console.print(t)
    png = plot_heatmap(table, grid, out / "sweep_heatmap.png", f"mean Map-Fusion ATE, {len(scenarios)} run(s)")
    console.print(f"{sims} simulation(s) for {left} fusion(s) this time; heatmap: {png}")


@app.command()
def tune(
    paths: Annotated[list[Path], typer.Argument(help="Scenario or family TOML files.")],
    trials: Annotated[int, typer.Option("--trials", "-n", min=1, help="Trials to add to the study.")] = 30,
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory for study.db and tune_sensitivity.png.")] = Path("tune"),
    storage: Annotated[Optional[str], typer.Option("--storage", help="Optuna storage URL (default sqlite:///OUT/study.db); "
                                                   "a shared one lets several processes work on one study.")] = None,
    study: Annotated[Optional[str], typer.Option("--study", help="Study name (default: the first file's stem).")] = None,
    range_: Annotated[Optional[list[str]], typer.Option("--range", help="NAME=LOW:HIGH, repeatable; replaces the default "
                                                        "ranges (lane_width_m 1.5:6, yaw_sigma_deg 2:40, "
                                                        "angle_weight_m_per_deg 0:4, search_radius_m 5:50).")] = None,
    start: Annotated[Optional[list[str]], typer.Option("--start", help="NAME=VALUE,... a first trial to try, repeatable.")] = None,
    penalty_m: Annotated[float, typer.Option("--penalty-m", min=0.0, help="Added to the objective per de-localised run (m).")] = 50.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the TPE sampler.")] = 0,
) -> None:
    """Optuna over lane width, yaw σ, angle weight and search radius: objective = mean Map-Fusion ATE
    plus a penalty per de-localisation, each scenario simulated once. The paper's defaults are the
    first trial; prints the best parameters against them and writes a sensitivity plot."""
    from sim.sweep import PAPER_DEFAULTS, TUNE_RANGES, plot_sensitivity, tune as run_study

    try:
        ranges = dict(TUNE_RANGES) if not range_ else {}
        for spec in range_ or []:
            name, sep, span = spec.partition("=")
            lo, sep2, hi = span.partition(":")
            if not sep or not sep2:
                raise InputError(f"--range {spec!r}: expected NAME=LOW:HIGH")
            try:
                ranges[name.strip()] = (float(lo), float(hi))
            except ValueError:
                raise InputError(f"--range {spec!r}: LOW and HIGH must be numbers") from None
        starts = []
        for spec in start or []:
            d = {}
            for part in spec.split(","):
                k, sep, v = part.partition("=")
                if not sep or k.strip() not in ranges:
                    raise InputError(f"--start {spec!r}: expected NAME=VALUE,... over the tuned parameters ({', '.join(ranges)})")
                try:
                    d[k.strip()] = float(v)
                except ValueError:
                    raise InputError(f"--start {spec!r}: {k} must be a number") from None
            starts.append(d)
        scenarios = _load_runs(paths)
        out.mkdir(parents=True, exist_ok=True)
        url = storage or f"sqlite:///{(out / 'study.db').resolve()}"
        name = study or paths[0].stem
        with _RunBar(trials, "trials") as bar:
            res = run_study(scenarios, trials, url, name, ranges, penalty_m, starts, seed,
                            on_trial=lambda n, v: bar.advance(not math.isfinite(v)))
    except InputError as exc:
        _fail(str(exc))
    t = Table(title=f"study {res.study_name}: {res.trials} trials over {len(scenarios)} run(s) ({res.storage})")
    t.add_column("parameter")
    t.add_column("paper", justify="right")
    t.add_column("best", justify="right")
    for k in ranges:
        t.add_row(k, f"{PAPER_DEFAULTS.get(k, float('nan')):g}", f"{res.best_params.get(k, float('nan')):.3g}")
    t.add_row("objective (m)", "–" if res.default_value is None else f"{res.default_value:.2f}", f"{res.best_value:.2f}")
    t.add_row("mean ATE (m)", "–" if res.default_mean_ate_m is None else f"{res.default_mean_ate_m:.2f}",
              f"{res.best_mean_ate_m:.2f}")
    console.print(t)
    png = plot_sensitivity(url, name, out / "tune_sensitivity.png")
    console.print(f"sensitivity plot: {png}")


@app.command()
def plot(
    run_dir: Annotated[Path, typer.Argument(help="A run directory (from mapfusion run or simulate).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="PNG to write (1200 × 1000 px).")],
) -> None:
    """Roads, truth, odometry, Map-Fusion, GPS fixes, GPS-denied zones and map priors; error over distance."""
    from .plot import plot_run

    try:
        plot_run(run_dir, out)
    except InputError as exc:
        _fail(str(exc))
    console.print(f"wrote {out}")


#: The demo drive: Helsinki in rain, an 80 m GPS-denied, visually degraded zone (an underpass),
#: stereo VO, GPS for the first 120 s only. Seed 7 is a drive where the zone falls on a stretch the
#: VO can bridge; on longer zones a VO that loses track de-localises, as the paper's DROID-SLAM does.
DEMO_SCENARIO = {
    "name": "demo-helsinki-rain",
    "map": "helsinki",
    "seed": 7,
    "duration_s": 480.0,
    "min_route_m": 2000.0,
    "weather": {"kind": "rain"},
    "odometry": {"kind": "vo"},
    "gps": {"mode": "init_only"},
    "tunnels": [{"start_m": 700.0, "end_m": 780.0}],
}


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")] = Path("mapfusion-demo"),
) -> None:
    """The main job on the bundled Helsinki map: one rain drive with a GPS-denied zone, VO odometry,
    GPS at the start only; baseline and Map-Fusion, the paper-style table and plot.png."""
    from sim.run import run_scenario
    from sim.scenario import scenario_from_dict

    sc = scenario_from_dict(DEMO_SCENARIO, "the demo scenario")
    with err_console.status("SUMO drive, sensors, baseline and Map-Fusion ..."):
        outcome = run_scenario(sc, out)
    m = outcome.metrics
    console.print(_paper_table([m], "Demo: Helsinki, rain, 80 m GPS-denied zone, VO, GPS at start only"))
    if "online_rmse_odometry_m" in m:
        console.print(
            f"online error (what a tracker sees, no alignment): odometry {m['online_rmse_odometry_m']:.1f} m RMSE, "
            f"Map-Fusion {m['online_rmse_mapfusion_m']:.1f} m; {m['map_priors']} map priors; "
            f"{m['driven_m'] / 1000:.2f} km in {m['duration_s']:.0f} s"
        )
    console.print(f"run directory: {out}  (plot: {out / 'plot.png'})")


def main() -> None:
    """Console-script entry point."""
    try:
        app()
    except InputError as exc:  # any bad input a command did not catch itself
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
