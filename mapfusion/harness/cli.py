"""The ``mapfusion`` command line (typer + rich).

The CLI owns printing, progress and exit codes: bad input exits 2 with one line on stderr, an
internal failure exits 1. Heavy modules are imported inside the commands so ``--help`` is quick.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os

import logging
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from mapfusion.errors import InputError

from .tables import paper_table

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
    _one_line(message)
    raise typer.Exit(code)


def _check_output_file(path: Path, option: str, inputs: dict[str, Path | str | None]) -> None:
    """Refuse, before any work, an output file that is a directory, cannot be created, or is one of
    the command's inputs (it would be overwritten)."""
    if path.is_dir():
        _fail(f"{option} {path} is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        _fail(f"{option} {path}: no such directory {parent}")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        _fail(f"{option} {path}: not writable")
    for name, given in inputs.items():
        if given is None or (name == "--map" and not Path(given).exists()):  # a built-in map's name
            continue
        if Path(given).resolve() == path.resolve():
            _fail(f"{option} {path} is also {name}: it would be overwritten")


def _check_output_dir(path: Path, option: str, inputs: list[Path] | tuple[Path, ...] = ()) -> None:
    """Refuse, before any work, an output folder that is an existing file (an input, or anything
    else: it would be replaced) or lies where nothing can be created."""
    if path.exists() and not path.is_dir():
        named = next((p for p in inputs if p.exists() and p.resolve() == path.resolve()), None)
        _fail(f"{option} {path} is {'an input' if named else 'a file'}, not a folder: it would be overwritten")
    existing = next((a for a in [path, *path.absolute().parents] if a.exists()), None)
    if existing is None or not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        _fail(f"{option} {path}: cannot create a folder under {existing}")


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
    spacing_m: Annotated[float, typer.Option(help="Way-point spacing in metres.", min=0.05, max=50.0)] = 1.0,
    no_cache: Annotated[bool, typer.Option("--no-cache", help="Rebuild even when a cached map exists.")] = False,
) -> None:
    """Build the processed road map of an OSM file (cached) and print its statistics."""
    from mapfusion.maps import resolve_map
    from mapfusion.roadmap import RoadMap, RoadMapConfig

    try:
        cfg = RoadMapConfig(spacing_m=spacing_m)
        path = resolve_map(osm)
        with err_console.status(f"building road map of {path.name} ..."):
            road = RoadMap.from_osm(path, cfg, cache=not no_cache)
    except InputError as exc:
        _fail(str(exc))
    stats = road.stats()
    if as_json:
        _print_json(stats.to_dict(), indent=2)
    else:
        console.print(_stats_table(stats, f"Road map: {path}"))


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
    from mapfusion import synthetic

    try:
        k = synthetic.SyntheticKind(kind)
    except ValueError:
        _fail(f"unknown map kind {kind!r}; known: {', '.join(x.value for x in synthetic.SyntheticKind)}")
    try:
        params = synthetic.parse_params(k, param or [])
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
    offset_extra_m: Annotated[float, typer.Option(help="Across-road offsets reach ±(road width + this), metres.", min=0.0, max=50.0)] = 3.0,
    heading_error_deg: Annotated[float, typer.Option(help="Heading errors uniform in ± this, degrees.", min=0.0, max=180.0)] = 20.0,
    poses_per_station: Annotated[int, typer.Option(help="Random poses per station and direction.", min=1, max=1000)] = 4,
    radius_m: Annotated[float, typer.Option(help="Matcher search radius, metres.", min=0.5, max=500.0)] = 20.0,
    angle_weight: Annotated[float, typer.Option("--angle-weight-m-per-deg", help="w in D = E + w·A, metres per degree.", min=0.0, max=100.0)] = 1.0,
    lane_width_m: Annotated[float, typer.Option(help="Lane width, metres (road width = lanes × lane width).", min=0.5, max=10.0)] = 3.0,
    seed: Annotated[int, typer.Option(help="Seed of offsets and heading errors.")] = 0,
    sequence: Annotated[bool, typer.Option("--sequence", help="Also drive through every junction (every entering road "
                                           "to every other road, errors correlated along the drive) and match the "
                                           "drives as sequences with road hypotheses (an HMM over the road graph, "
                                           "mapfusion.hypotheses), beside the single-frame matcher on the same poses.")] = False,
) -> None:
    """Stress-test the road matcher around every junction; match rate overall and by junction kind."""
    from mapfusion.maps import resolve_map
    from mapfusion.roadmap import RoadMap

    from .stress import StressConfig, run_sequence_stress, run_stress

    try:
        cfg = StressConfig(
            offset_extra_m=offset_extra_m,
            heading_error_deg=heading_error_deg,
            poses_per_station=poses_per_station,
            radius_m=radius_m,
            angle_weight_m_per_deg=angle_weight,
            seed=seed,
            lane_width_m=lane_width_m,
        )
        path = resolve_map(osm)
        with err_console.status(f"matching poses around the junctions of {path.name} ..."):
            road = RoadMap.from_osm(path)
            result = run_stress(road, cfg)
        seq = None
        if sequence:
            with err_console.status(f"driving through the junctions of {path.name} ..."):
                seq = run_sequence_stress(road, cfg)
    except InputError as exc:
        _fail(str(exc))
    if as_json:
        d = result.to_dict()
        if seq is not None:  # the sequence figures lead; the station test stays under "stations"
            d = {**seq.to_dict(), "stations": d}
        _print_json(d, indent=2)
        return
    if seq is not None:
        _print_sequence_stress(path.name, seq)
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


def _print_sequence_stress(name: str, seq) -> None:
    t = Table(title=f"Junction drives: {name} (the same poses, single-frame and as sequences)")
    for col in ("junction kind", "junctions", "drives", "poses", "single-frame", "sequence"):
        t.add_column(col, justify="right")
    for k in seq.by_kind:
        t.add_row(k.kind, str(k.junctions), f"{k.drives:,}", f"{k.poses:,}", f"{100 * k.rate_single:.1f} %",
                  f"{100 * k.rate:.1f} %")
    t.add_row("all", "", "", f"{seq.poses:,}", f"{100 * seq.rate_single:.1f} %", f"{100 * seq.rate:.1f} %", style="bold")
    console.print(t)


@scenarios_app.command("generate")
def scenarios_generate(
    family: Annotated[str, typer.Option(
        "--family", help="clear | rain | rain-tunnel | heavy-rain | intersections | kidnapped | kitti")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Family file to write (TOML).")],
    maps: Annotated[Optional[list[str]], typer.Option("--maps", help="Maps (built-in names or OSM paths), repeatable.")] = None,
    seeds: Annotated[Optional[int], typer.Option("--seeds", help="Seeds 1..N.", min=1)] = None,
    weather: Annotated[Optional[list[str]], typer.Option("--weather", help="clear | rain | heavy_rain, repeatable.")] = None,
    odometry: Annotated[Optional[list[str]], typer.Option("--odometry", help="vo | vio | mono | droid | orb-vio | vo+wheel | vio+wheel, "
                                                          "repeatable.")] = None,
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
        if out.is_dir():
            raise InputError(f"--out {out} is a directory")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    except InputError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"--out {out}: cannot write ({exc.strerror})")
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
    offset: Annotated[Optional[int], typer.Option("--offset", help="The track point (raw frame) of the sequence's "
                                                  "frame 0, when the track covers a longer recording (KITTI 08: "
                                                  "1100). Default: found from the step lengths.")] = None,
) -> None:
    """A KITTI sequence as a run directory: truth.tum in the map's ENU frame (georeferenced to the RTK
    track with the antenna's lever arm), gps.csv from the track, import.json with the fit's residual and the
    track offset used."""
    from mapfusion.kitti import import_kitti, write_import
    from mapfusion.maps import resolve_map
    from mapfusion.roadmap import RoadMap

    _check_output_dir(out, "--out", [poses, times, gps])
    if gps_at not in ("camera", "antenna"):
        _fail(f"--gps-at is camera or antenna, got {gps_at!r}")
    try:
        mp = resolve_map(map_path) if map_path else resolve_map(poses.parent / "map.osm")
        road = RoadMap.from_osm(mp)
        imp = import_kitti(poses, times, gps, road.projection, offset=offset)
        road.check_covers(imp.truth_enu[:, :2, 3], f"{gps}: the georeferenced drive on the map {mp}")
        write_import(out, imp, road.projection, str(Path(mp).resolve()), gps_at_camera=gps_at == "camera")
    except InputError as exc:
        _fail(str(exc))
    g = imp.georef
    how = "given" if offset is not None else "found"
    console.print(f"{len(imp.t_s):,} frames → {out}; track offset {imp.offset} ({how}); fit residual {g.residual_rmse_m:.3f} m RMSE "
                  f"(max {g.residuals_m.max():.2f} m, {int(imp.filled.sum())} filled track points left out); lever arm (camera x right, y down, z forward) "
                  f"{g.lever_arm_cam_m[0]:+.2f}, {g.lever_arm_cam_m[1]:+.2f}, {g.lever_arm_cam_m[2]:+.2f} m")


@import_app.command("bag")
def import_bag_cmd(
    bag: Annotated[Path, typer.Option("--bag", help="A ROS 1 (.bag) or ROS 2 (folder, sqlite3 or mcap) bag.")],
    odometry_topic: Annotated[str, typer.Option("--odometry-topic", help="Its nav_msgs/Odometry topic.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory to write.")],
    gps_topic: Annotated[Optional[str], typer.Option("--gps-topic", help="Its sensor_msgs/NavSatFix topic.")] = None,
    imu_topic: Annotated[Optional[str], typer.Option("--imu-topic", help="Its sensor_msgs/Imu topic.")] = None,
    wheel_topic: Annotated[Optional[str], typer.Option("--wheel-topic", help="Its wheel speed: a "
                                                       "geometry_msgs/TwistStamped topic, twist.linear.x in m/s.")] = None,
) -> None:
    """A bag's odometry, GPS, IMU and wheel speed as files: odometry.tum (body convention), gps.csv,
    imu.csv, wheel.csv (t,speed_mps)."""
    from mapfusion.bags import read_bag
    from mapfusion.formats import matrices_to_tum, write_gps_csv, write_imu_csv, write_tum, write_wheel_csv

    _check_output_dir(out, "--out", [bag])
    try:
        data = read_bag(bag, odometry_topic, gps_topic, imu_topic, wheel_topic)
    except InputError as exc:
        _fail(str(exc))
    out.mkdir(parents=True, exist_ok=True)
    if data.wheel is not None:
        write_wheel_csv(out / "wheel.csv", *data.wheel)
    xyz, q = matrices_to_tum(data.poses)
    write_tum(out / "odometry.tum", data.t_s, xyz, q, header=f"{odometry_topic} of {bag}")
    if data.gps is not None:
        g = data.gps
        write_gps_csv(out / "gps.csv", g.t_s, g.lat_deg, g.lon_deg, g.alt_m, g.sigma_m)
    if data.imu is not None:
        write_imu_csv(out / "imu.csv", *data.imu)
    console.print(f"{len(data.t_s):,} odometry poses, {0 if data.gps is None else len(data.gps)} GPS fixes "
                  f"({data.gps_without_fix} without a fix skipped), {0 if data.imu is None else len(data.imu[0])} IMU "
                  f"samples → {out}" + (" (optical child frame: read as camera axes)" if data.camera_frame else ""))


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
    from sim.network import RouteError, SimulationError
    from sim.scenario import load_scenario

    from .pipeline import simulate_scenario, write_simulation

    _check_output_dir(out, "--out", [scenario] + ([truth] if truth else []))
    try:
        sc = load_scenario(scenario)
        if truth is not None:
            if not truth.exists():
                raise InputError(f"{truth}: no such file or directory")
            sc = sc.replace(truth=str(truth.resolve()))
        with _SimBar(sc.name, sc.duration_s) as bar:
            sim = simulate_scenario(sc, progress=bar.update)
        write_simulation(out, sim)
    except RouteError as exc:
        _fail(f"{scenario}: {exc}")
    except SimulationError as exc:
        _fail(f"{scenario}: {exc}", code=1)
    except InputError as exc:
        _fail(str(exc))
    n_odo, n_gps = len(sim.sensors.odometry.t_s), len(sim.sensors.gps.t_s)
    if sim.drive is None:
        console.print(f"{sc.name}: sensors on the recorded truth {sc.truth} ({len(sim.truth):,} frames): "
                      f"{n_odo:,} odometry frames, {n_gps} GPS fixes → {out}")
        return
    d = sim.drive
    console.print(f"{sc.name}: {len(d.ego):,} frames, {d.ego.t_s[-1]:.1f} s simulated, {d.ego.distance_m[-1]:,.0f} m driven "
                  f"(route {d.route_length_m:,.0f} m), {d.realtime_factor:,.0f}× real time; "
                  f"{n_odo:,} odometry frames, {n_gps} GPS fixes → {out}")


class _Bar:
    """A rich progress bar on stderr, silent off a terminal; subclasses say what it counts."""

    def __init__(self, *columns, total: float | None, description: str = "", transient: bool = True) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), *columns, TimeElapsedColumn(),
                            console=err_console, transient=transient, disable=not err_console.is_terminal)
        self.task = self.bar.add_task(description, total=total)

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        self.bar.__exit__(*exc)


class _SimBar(_Bar):
    """Simulated seconds of a SUMO drive."""

    def __init__(self, name: str, total_s: float) -> None:
        from rich.progress import TextColumn

        super().__init__(TextColumn("{task.completed:.0f}/{task.total:.0f} s"), total=total_s,
                         description=f"simulating {name}")

    def update(self, t: float, total: float) -> None:
        self.bar.update(self.task, completed=t)


@app.command()
def fuse(
    map_path: Annotated[str, typer.Option("--map", help="OSM file or built-in map name.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Estimate to write (TUM, map ENU frame).")],
    odometry: Annotated[Optional[Path], typer.Option("--odometry", help="Odometry poses in its own frame (TUM, or "
                                                     "KITTI with --times); or give --bag.")] = None,
    bag: Annotated[Optional[Path], typer.Option("--bag", help="A ROS 1 (.bag) or ROS 2 (folder, sqlite3 or mcap) bag "
                                                "instead of the files: with --odometry-topic, --gps-topic, --imu-topic.")] = None,
    odometry_topic: Annotated[Optional[str], typer.Option("--odometry-topic", help="The bag's nav_msgs/Odometry topic.")] = None,
    gps_topic: Annotated[Optional[str], typer.Option("--gps-topic", help="The bag's sensor_msgs/NavSatFix topic.")] = None,
    imu_topic: Annotated[Optional[str], typer.Option("--imu-topic", help="The bag's sensor_msgs/Imu topic (read and "
                                                     "checked, as --imu).")] = None,
    bag_covariance: Annotated[bool, typer.Option("--bag-covariance/--no-bag-covariance", help="With --bag: the "
                                                 "odometry's published pose covariance, where it grows, sets the "
                                                 "engine's odometry_sigma_per_m (its growth per metre driven).")] = True,
    wheel_topic: Annotated[Optional[str], typer.Option("--wheel-topic", help="The bag's wheel speed "
                                                       "(geometry_msgs/TwistStamped, twist.linear.x m/s): fused with "
                                                       "--imu-topic's yaw rate as a second motion source.")] = None,
    out_bag: Annotated[Optional[Path], typer.Option("--out-bag", help="Also write the online estimate (nav_msgs/Odometry, "
                                                    "frame map, child base_link) and the map priors (a MarkerArray) "
                                                    "as a bag: NAME.bag is ROS 1, any other name a ROS 2 bag folder "
                                                    "(MCAP storage).")] = None,
    gps: Annotated[Optional[Path], typer.Option("--gps", help="GPS CSV (t,lat,lon,alt,sigma_m).")] = None,
    imu: Annotated[Optional[Path], typer.Option("--imu", help="IMU CSV (t,ax,ay,az,gx,gy,gz; body frame x forward, "
                                                "y left, z up): with --wheel its gz is the yaw rate fused; alone it "
                                                "is read and checked only.")] = None,
    wheel: Annotated[Optional[Path], typer.Option("--wheel", help="Wheel-speed CSV (t,speed_mps): with --imu a "
                                                  "second motion source beside the odometry (bridges VO outages, "
                                                  "replaces VO jumps).")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="TOML with a [mapfusion] table (FusionConfig).")] = None,
    odometry_format: Annotated[str, typer.Option("--odometry-format", help="tum | kitti")] = "tum",
    times: Annotated[Optional[Path], typer.Option("--times", help="Timestamps, one a line (KITTI times.txt).")] = None,
    odometry_frame: Annotated[str, typer.Option("--odometry-frame", help="body (x fwd, y left, z up) | camera (x right, y down, z fwd)")] = "body",
    no_map: Annotated[bool, typer.Option("--no-map", help="The baseline: same GPS use, no map priors.")] = False,
    smoothed: Annotated[Optional[Path], typer.Option("--smoothed", help="Also write the smoothed trajectory (TUM).")] = None,
    gps_until_s: Annotated[Optional[float], typer.Option("--gps-until-s", help="Use GPS fixes only this many seconds "
                                                         "from the first odometry frame (the paper's KITTI protocol: "
                                                         "GPS for initialisation only).", min=0.0)] = None,
    start_region: Annotated[Optional[str], typer.Option("--start-region", help="LAT,LON,RADIUS_M: a cold start "
                                                        "without GPS — the vehicle starts on a road within RADIUS_M "
                                                        "metres of LAT,LON and the odometry's shape finds it on the "
                                                        "map (issue 17); the odometry is taken as metric unless "
                                                        "--scale-unknown. The estimate begins once found.")] = None,
    scale_unknown: Annotated[bool, typer.Option("--scale-unknown", help="With --start-region: the odometry's scale "
                                                "is not known (a monocular VO, a biased one): the search finds it "
                                                "with the position, within --scale-range.")] = False,
    scale_range: Annotated[str, typer.Option("--scale-range", help="LO,HI: with --scale-unknown, the scales (map "
                                             "metres per odometry unit) searched over, log-uniformly.")] = "0.5,2.0",
    plot_search: Annotated[Optional[Path], typer.Option("--plot-search", help="With --start-region: also draw the "
                                                        "search (PNG): its particles over the map at four moments up "
                                                        "to the vehicle found.")] = None,
) -> None:
    """Run the engine on recorded odometry and GPS with an OSM map; write the online (causal) estimate."""
    from mapfusion.replay import OdometryFormat, OdometryFrame, load_fusion_config

    from .pipeline import RecordedInputs, fuse_recorded_to_files

    given = {"--map": map_path, "--odometry": odometry, "--gps": gps, "--imu": imu, "--config": config, "--times": times,
             "--bag": bag, "--wheel": wheel}
    _check_output_file(out, "--out", given)
    if smoothed is not None:
        _check_output_file(smoothed, "--smoothed", {**given, "--out": out})
    if plot_search is not None:
        if start_region is None:
            _fail("--plot-search draws the search of --start-region: give both")
        _check_output_file(plot_search, "--plot-search", {**given, "--out": out})
    if (odometry is None) == (bag is None):
        _fail("give --odometry FILE or --bag PATH (with --odometry-topic), not both or neither")
    if out_bag is not None:
        if out_bag.exists():
            _fail(f"--out-bag {out_bag} exists: a bag is never overwritten")
        _check_output_file(out_bag, "--out-bag", {**given, "--out": out})
    if bag is not None:
        if not odometry_topic:
            _fail("--bag needs --odometry-topic (a nav_msgs/Odometry topic)")
        if gps is not None or imu is not None or times is not None or wheel is not None:
            _fail("--bag takes its GPS, IMU and wheel speed from --gps-topic, --imu-topic and --wheel-topic, not --gps, "
                  "--imu, --wheel or --times")
        if wheel_topic and not imu_topic:
            _fail("--wheel-topic needs --imu-topic (its gyro gives the yaw rate)")
        _fuse_bag(map_path, bag, odometry_topic, gps_topic, imu_topic, gps_until_s, config, no_map, out, smoothed,
                  out_bag, wheel_topic, bag_covariance)
        return
    if odometry_topic or gps_topic or imu_topic or wheel_topic:
        _fail("--odometry-topic, --gps-topic, --imu-topic and --wheel-topic go with --bag")
    try:
        try:
            fmt, frame = OdometryFormat(odometry_format), OdometryFrame(odometry_frame)
        except ValueError as exc:
            raise InputError(f"{exc}; --odometry-format is tum or kitti, --odometry-frame is body or camera") from None
        cfg = load_fusion_config(config, **({"use_map": False} if no_map else {}),
                                 **(_scale_search(scale_range) if scale_unknown else {}))
        if scale_unknown and start_region is None:
            _fail("--scale-unknown goes with --start-region (a GPS initialisation measures the scale itself)")
        if wheel is not None and imu is None:
            _fail("--wheel needs --imu (its gyro gives the yaw rate)")
        region = parse_start_region(start_region) if start_region is not None else None
        inputs = RecordedInputs(map_path, odometry, fmt, frame, times, gps, gps_until_s, imu, wheel, region)
        with _FrameBar() as bar:
            if out_bag is None:  # streamed, in flat memory
                eng, n = fuse_recorded_to_files(inputs, cfg, out, smoothed, f" ({'no map' if no_map else 'with map'})",
                                                progress=bar.update)
            else:  # the bag's covariances need every frame's σ: kept whole
                eng, n = _fuse_files_with_bag(inputs, cfg, out, smoothed, out_bag, no_map, bar.update)
    except InputError as exc:
        _fail(str(exc))
    _require_initialised(eng)
    _fuse_summary(eng, n, out)
    if plot_search is not None and region is not None:
        _draw_search(inputs, cfg, region, plot_search)


def _draw_search(inputs, cfg, region: tuple[float, float, float], out: Path) -> None:
    """``fuse --plot-search``: the cold start's search drawn (run again on the same odometry, same seed)."""
    import numpy as np

    from mapfusion.maps import resolve_map
    from mapfusion.relocalise import Region
    from mapfusion.replay import read_odometry
    from mapfusion.roadmap import RoadMap

    from .searchplot import plot_search, search_snapshots

    road = RoadMap.from_osm(resolve_map(inputs.map))
    _, poses = read_odometry(inputs.odometry, inputs.odometry_format, inputs.times, inputs.odometry_frame)
    planar = np.column_stack([poses[:, 0, 3], poses[:, 1, 3], np.arctan2(poses[:, 1, 0], poses[:, 0, 0])])
    x, y = road.projection.to_enu(region[0], region[1])
    reg = Region(float(x), float(y), region[2])
    shots, found = search_snapshots(road, cfg, reg, planar)
    plot_search(road, reg, shots, found, out)
    console.print(f"search drawn → {out}")


def _scale_search(text: str) -> dict[str, float]:
    """``--scale-range LO,HI`` → the config overrides of a search for the scale, or an InputError."""
    try:
        lo, hi = (float(p) for p in text.split(","))
    except ValueError:
        raise InputError(f"--scale-range {text!r}: expected LO,HI (two numbers)") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi <= 1e6):
        raise InputError(f"--scale-range {text!r}: 0 < LO < HI ≤ 1e6 (map metres per odometry unit)")
    return {"reloc_scale_min": lo, "reloc_scale_max": hi}


def parse_start_region(text: str) -> tuple[float, float, float]:
    """``LAT,LON,RADIUS_M`` → (lat, lon, radius_m), or an InputError naming --start-region."""
    parts = text.split(",")
    try:
        lat, lon, radius = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"--start-region {text!r}: expected LAT,LON,RADIUS_M (three numbers)") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and 0.0 < radius <= 100_000.0):
        raise InputError(f"--start-region {text!r}: latitude in [-90, 90], longitude in [-180, 180], "
                         "radius in (0, 100000] m")
    return lat, lon, radius


def _require_initialised(eng) -> None:
    if not eng.initialised and eng.searching_from_region:
        _fail(f"the vehicle was not found in the start region: the road-network search did not converge over "
              f"the drive ({eng.counters.frames} frames); a longer drive with turns, or a smaller region")
    if not eng.initialised:
        _fail("the engine never initialised: it needs GPS fixes while the vehicle moves "
              f"(got {eng.counters.gps_before_init} fixes, {eng.scale_samples} scale samples)")


def _fuse_files_with_bag(inputs, cfg, out: Path, smoothed, out_bag: Path, no_map: bool, progress):
    from mapfusion.bags import BagKind

    from .pipeline import fuse_recorded, write_estimate_bag, write_estimates

    sigmas: list[float] = []
    res = fuse_recorded(inputs, cfg, progress=progress, on_frame=lambda e: sigmas.append(e.position_sigma_m))
    if res.engine.initialised:
        n = write_estimates(res, out, smoothed, f" ({'no map' if no_map else 'with map'})")
        write_estimate_bag(out_bag, BagKind.for_path(out_bag), res, sigmas)
        return res.engine, n
    return res.engine, 0


def _fuse_bag(map_path, bag, odometry_topic, gps_topic, imu_topic, gps_until_s, config, no_map, out, smoothed,
              out_bag, wheel_topic=None, bag_covariance: bool = True) -> None:
    """``fuse --bag``: the engine on a bag's topics."""
    from mapfusion.bags import BagKind
    from mapfusion.replay import load_fusion_config

    from .pipeline import BagInputs, fuse_bag, write_estimate_bag, write_estimates

    try:
        cfg = load_fusion_config(config, **({"use_map": False} if no_map else {}))
        with _FrameBar() as bar:
            res, data, sigmas = fuse_bag(BagInputs(map_path, bag, odometry_topic, gps_topic, imu_topic, gps_until_s,
                                                   wheel_topic, bag_covariance), cfg, progress=bar.update)
    except InputError as exc:
        _fail(str(exc))
    eng = res.engine
    _require_initialised(eng)
    n = write_estimates(res, out, smoothed, f" ({'no map' if no_map else 'with map'})")
    if out_bag is not None:
        write_estimate_bag(out_bag, BagKind.for_path(out_bag), res, sigmas)
    if data.camera_frame:
        err_console.print(f"{odometry_topic}: an optical (camera) child frame: read as x right, y down, z forward")
    if eng.cfg.odometry_sigma_per_m != cfg.odometry_sigma_per_m:
        err_console.print(f"{odometry_topic}: its pose covariance sets odometry_sigma_per_m = "
                          f"{eng.cfg.odometry_sigma_per_m:.4g} m/m (--no-bag-covariance keeps {cfg.odometry_sigma_per_m:g})")
    if data.gps_without_fix:
        err_console.print(f"{gps_topic}: {data.gps_without_fix} message(s) without a fix (status −1) skipped")
    _fuse_summary(eng, n, out)


def _fuse_summary(eng, n: int, out: Path) -> None:
    c = eng.counters
    console.print(f"{n:,} poses → {out}; scale {eng.scale:.4f} ± {eng.scale_sigma or 0:.4f}, "
                  f"initialised at t = {eng.initialised_at:.1f} s; map priors {c.map_priors}, GPS used {c.gps_used} "
                  f"(rejected {c.gps_rejected}: {c.gps_rejected_gate} by the gate, {c.gps_rejected_time} for their time, "
                  f"{c.gps_rejected_invalid} invalid), odometry priors {c.odometry_priors}, "
                  f"recoveries {c.recoveries}, odometry jumps bridged {c.odometry_jumps}")
    if c.gps_relocalisations:
        console.print(f"GPS re-localisations {c.gps_relocalisations} (consistent fixes disagreed with the estimate), "
                      f"{c.gps_rescales} of them re-scaling the odometry (the scale above is the last)")
    if c.wheel_frames or c.odometry_vetoed or eng.wheel_scale != 1.0:
        console.print(f"wheel + gyro: {c.wheel_frames} frames made where the odometry had none, {c.odometry_vetoed} "
                      f"odometry steps replaced; wheel scale {eng.wheel_scale:.4f}, gyro bias "
                      f"{eng.gyro_bias_radps:.5f} rad/s")


class _FrameBar(_Bar):
    """Frames fused."""

    def __init__(self) -> None:
        from rich.progress import TextColumn

        super().__init__(TextColumn("{task.completed:,}/{task.total:,} frames"), total=None, description="fusing")

    def update(self, k: int, n: int) -> None:
        self.bar.update(self.task, completed=k, total=n)


@app.command()
def evaluate(
    truth: Annotated[Path, typer.Option("--truth", help="Ground truth (TUM).")],
    estimate: Annotated[Path, typer.Option("--estimate", help="Estimate (TUM), e.g. from mapfusion fuse.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON.")] = False,
    max_dt_s: Annotated[float, typer.Option(help="Poses match when their times differ by at most this, seconds.", min=1e-6, max=10.0)] = 0.02,
    delocalization_m: Annotated[float, typer.Option(help="ATE above this counts as de-localised, metres.", min=0.01, max=1e6)] = 20.0,
    scale: Annotated[bool, typer.Option("--scale", help="KITTI's t_err / r_err after one fitted global scale "
                                        "(as KITTI scores monocular odometry).")] = False,
) -> None:
    """ATE (the paper's), online error (no alignment; lateral and longitudinal parts), RPE per 100 m and
    KITTI's odometry metric (t_err %, r_err deg/100 m over 100–800 m segments)."""
    from .pipeline import evaluate_files

    try:
        out = evaluate_files(truth, estimate, max_dt_s, delocalization_m, fit_scale=scale)
    except InputError as exc:
        _fail(str(exc))
    _print_figures(out, as_json, f"{estimate.name} against {truth.name}", "metric")


def _check_scheduler(scheduler: str | None) -> None:
    from .batch import check_scheduler

    if scheduler is not None:
        try:
            check_scheduler(scheduler)
        except InputError as exc:
            _fail(str(exc))


@app.command("odometry-stats")
def odometry_stats_cmd(
    truth: Annotated[Path, typer.Option("--truth", help="Ground truth poses (TUM, or KITTI with --times).")],
    odometry: Annotated[Path, typer.Option("--odometry", help="The odometry's poses, same format and frame.")],
    fmt: Annotated[str, typer.Option("--format", help="tum | kitti")] = "tum",
    times: Annotated[Optional[Path], typer.Option("--times", help="KITTI times.txt (with --format kitti).")] = None,
    frame: Annotated[str, typer.Option("--frame", help="body | camera (KITTI's poses are camera)")] = "body",
    as_json: Annotated[bool, typer.Option("--json", help="Print the statistics as JSON.")] = False,
) -> None:
    """What an odometry's error is made of against the truth of the same drive: KITTI's t_err and
    r_err after a fitted scale, yaw drift, scale per 100 m window and its random walk, the start's
    scale bias, lateral error and its spectrum, jumps, the step errors' autocorrelation."""
    from mapfusion.metrics import associate, odometry_stats
    from mapfusion.replay import OdometryFormat, OdometryFrame, read_odometry

    try:
        try:
            f, fr = OdometryFormat(fmt), OdometryFrame(frame)
        except ValueError as exc:
            raise InputError(f"{exc}; --format is tum or kitti, --frame is body or camera") from None
        tt, gt = read_odometry(truth, f, times, fr)
        to, od = read_odometry(odometry, f, times, fr)
        ia, ib = associate(to, tt)
        if len(ia) < 20:
            raise InputError(f"{odometry}: only {len(ia)} poses match {truth} in time")
        stats = odometry_stats(tt[ib], gt[ib], od[ia])
    except InputError as exc:
        _fail(str(exc))
    d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in stats.__dict__.items()}
    _print_figures(d, as_json, f"{odometry.name} against {truth.name}", "statistic")


def _print_figures(figures: dict, as_json: bool, title: str, what: str) -> None:
    """Named figures as strict JSON, or as a two-column table (None as –, lists joined)."""
    if as_json:
        _print_json(figures, indent=2)
        return
    t = Table(title=title)
    t.add_column(what)
    t.add_column("value", justify="right")
    for k, v in figures.items():
        text = ("–" if v is None else ", ".join(f"{x:.3f}" for x in v) if isinstance(v, list)
                else f"{v:.4g}" if isinstance(v, float) else str(v))
        t.add_row(k, text)
    console.print(t)


def _default_workers() -> int:
    return max(1, os.cpu_count() or 1)


def _load_runs(paths: list[Path]):
    """Scenarios of every file, the unavailable ones reported and left out; exit 2 on bad input."""
    from sim.scenario import load_family

    from .estimators import load_class

    try:
        families = [load_family(p) for p in paths]
        for use in sorted({s.use for fam in families for sc in fam.scenarios for s in sc.estimators if s.use}):
            load_class(use)  # (every estimator's class importable before any run starts)
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


class _RunBar(_Bar):
    """Runs (or fusions, trials) done, failed and remaining."""

    def __init__(self, total: int, label: str = "runs") -> None:
        from rich.progress import TextColumn, TimeRemainingColumn

        self.done = self.failed = 0
        self.total = total
        super().__init__(TextColumn("{task.fields[done]} done, [red]{task.fields[failed]} failed[/], "
                                    "{task.fields[left]} remaining"), TimeRemainingColumn(),
                         total=total, description=label, transient=False)
        self.bar.update(self.task, done=0, failed=0, left=total)

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
    from .batch import plan_runs, run_logged

    _check_output_dir(out, "--out", paths)
    _check_scheduler(scheduler)
    scenarios = _load_runs(paths)
    out.mkdir(parents=True, exist_ok=True)
    todo, changed = plan_runs(scenarios, out / "results.jsonl")
    left = len(todo)
    if left < len(scenarios):
        err_console.print(f"resuming: {len(scenarios) - left} of {len(scenarios)} runs already in {out / 'results.jsonl'}")
    if changed:
        err_console.print(f"running again {len(changed)} run(s) whose scenario changed since their result: "
                          + ", ".join(changed[:5]) + (" ..." if len(changed) > 5 else ""), highlight=False)
    with _RunBar(left) as bar:
        rows, _ = run_logged(scenarios, out, workers=workers or _default_workers(), plot=not no_plot,
                             scheduler=scheduler, on_row=lambda row: bar.advance("error" in row))
    console.print(paper_table(rows, f"ATE over {len(rows)} run(s) → {out}", width=console.width))
    failed_rows = [r for r in rows if "error" in r]
    for r in failed_rows:
        err_console.print(f"[red]{r['scenario']} failed:[/] {r['error']}", highlight=False)
    for r in rows:
        for name, why in r.get("estimator_errors", {}).items():
            err_console.print(f"[red]{r['scenario']}: estimator {name} failed:[/] {why}", highlight=False)
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
    from .sweep import plan_sweep, plot_heatmap, run_sweep

    _check_output_dir(out, "--out", paths)
    _check_scheduler(scheduler)
    scenarios = _load_runs(paths)
    try:
        plan = plan_sweep(scenarios, param or [], variant or [], out)
    except InputError as exc:
        _fail(str(exc))
    out.mkdir(parents=True, exist_ok=True)
    if plan.left < plan.total:
        err_console.print(f"resuming: {plan.total - plan.left} of {plan.total} fusions already in {plan.results_path}")
    if plan.changed:
        err_console.print(f"running again {len(plan.changed)} scenario(s) changed since their results: "
                          + ", ".join(plan.changed[:5]) + (" ..." if len(plan.changed) > 5 else ""), highlight=False)
    with _RunBar(plan.left, "fusions") as bar:
        table, sims = run_sweep(plan, workers or _default_workers(), scheduler, on_row=lambda r: bar.advance("error" in r))
    grid, left = plan.grid, plan.left
    t = Table(title=f"mean ATE (m) over {len(scenarios)} run(s) per grid point")
    for k in grid:
        t.add_column(k, justify="right")
    extra = sorted({k[4:-2] for v in table.values() for k in v if k.startswith("ate_")} - {"odometry", "mapfusion"})
    for c in ("runs", "failed", "odometry", "+ Map-Fusion", "de-localised", *extra):
        t.add_column(c, justify="right")
    for v in table.values():
        t.add_row(*[str(v["params"][k]) for k in grid], str(v["runs"]), str(v["failed"]), f"{v['ate_odometry_m']:.2f}",
                  f"{v['ate_mapfusion_m']:.2f}", str(v["delocalized"]), *[f"{v[f'ate_{e}_m']:.2f}" for e in extra])
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
    from .sweep import (PAPER_DEFAULTS, fail_orphaned_trials, open_storage, parse_ranges, parse_starts,
                        plot_sensitivity, tune as run_study)

    _check_output_dir(out, "--out", paths)
    try:
        ranges = parse_ranges(range_ or [])
        starts = parse_starts(start or [], ranges)
        scenarios = _load_runs(paths)
        name = study or paths[0].stem
        opened = open_storage(storage) if storage else None  # a shared storage: checked before any work
        out.mkdir(parents=True, exist_ok=True)
        url = storage or f"sqlite:///{(out / 'study.db').resolve()}"
        with contextlib.ExitStack() as stack:
            if opened is None:  # our own study.db: while we hold its lock no other tune uses it
                stack.enter_context(_exclusive_lock(out / "study.db.lock", "--out"))
                opened = open_storage(url, "--out")
                orphans = fail_orphaned_trials(opened, name)
                if orphans:
                    err_console.print(f"{orphans} trial(s) left running by a killed tune marked failed")
            with _RunBar(trials, "trials") as bar:
                res = run_study(scenarios, trials, opened, name, ranges, penalty_m, starts, seed,
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


@contextlib.contextmanager
def _exclusive_lock(path: Path, option: str):
    """An exclusive lock on ``path`` for the block (released when the process dies, however it dies)."""
    import fcntl

    with open(path, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _fail(f"{option} {path.parent}: another mapfusion tune is working on this study")
        yield


@app.command()
def plot(
    run_dir: Annotated[Path, typer.Argument(help="A run directory (from mapfusion run or simulate).")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Picture to write (PNG: 1200 × 1000 px; or "
                                                "any format matplotlib writes, by its extension).")] = None,
    html: Annotated[Optional[Path], typer.Option("--html", help="Interactive map to write (Leaflet via folium; works "
                                                 "offline, OpenStreetMap tiles beneath when online).")] = None,
) -> None:
    """Roads, truth, odometry, Map-Fusion, GPS fixes, GPS-denied zones and map priors; error over distance."""
    from .plot import plot_run

    if out is None and html is None:
        _fail("give --out FILE.png and/or --html FILE.html")
    for opt, path in (("--out", out), ("--html", html)):
        if path is not None:
            _check_output_file(path, opt, {"RUN": run_dir})
    try:
        if out is not None:
            plot_run(run_dir, out)
            console.print(f"wrote {out}")
        if html is not None:
            from .webmap import write_html

            write_html(run_dir, html)
            console.print(f"wrote {html}")
    except InputError as exc:
        _fail(str(exc))


@app.command()
def export(
    run_dir: Annotated[Path, typer.Argument(help="A run directory (from mapfusion run, simulate or import).")],
    geojson: Annotated[Optional[Path], typer.Option("--geojson", help="GeoJSON (RFC 7946) to write: truth, estimates, "
                                                    "GPS fixes, map priors, GPS-denied zones.")] = None,
    gpx: Annotated[Optional[Path], typer.Option("--gpx", help="GPX 1.1 to write: a track per trajectory.")] = None,
    bag: Annotated[Optional[Path], typer.Option("--bag", help="The run's sensors as a bag (NAME.bag: ROS 1, any other "
                                                "name: a ROS 2 bag folder, MCAP): /odom (nav_msgs/Odometry), "
                                                "/gps/fix (sensor_msgs/NavSatFix), /imu (sensor_msgs/Imu).")] = None,
) -> None:
    """A run for GIS tools (QGIS, geojson.io, kepler.gl), GPS software and ROS: GeoJSON, GPX, a bag."""
    from .export import write_geojson, write_gpx, write_sensor_bag

    if geojson is None and gpx is None and bag is None:
        _fail("give --geojson FILE, --gpx FILE and/or --bag PATH")
    for opt, path in (("--geojson", geojson), ("--gpx", gpx), ("--bag", bag)):
        if path is not None:
            _check_output_file(path, opt, {"RUN": run_dir})
    if bag is not None and bag.exists():
        _fail(f"--bag {bag} exists: a bag is never overwritten")
    try:
        for path, write in ((geojson, write_geojson), (gpx, write_gpx), (bag, write_sensor_bag)):
            if path is not None:
                write(run_dir, path)
                console.print(f"wrote {path}")
    except InputError as exc:
        _fail(str(exc))


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
    from .pipeline import run_scenario
    from sim.scenario import scenario_from_dict

    _check_output_dir(out, "--out")
    sc = scenario_from_dict(DEMO_SCENARIO, "the demo scenario")
    with err_console.status("SUMO drive, sensors, baseline and Map-Fusion ..."):
        outcome = run_scenario(sc, out)
    m = outcome.metrics
    console.print(paper_table([m], "Demo: Helsinki, rain, 80 m GPS-denied zone, VO, GPS at start only"))
    if "online_rmse_odometry_m" in m:
        console.print(
            f"online error (what a tracker sees, no alignment): odometry {m['online_rmse_odometry_m']:.1f} m RMSE, "
            f"Map-Fusion {m['online_rmse_mapfusion_m']:.1f} m; {m['map_priors']} map priors; "
            f"{m['driven_m'] / 1000:.2f} km in {m['duration_s']:.0f} s"
        )
    console.print(f"run directory: {out}  (plot: {out / 'plot.png'})")


@app.command()
def noise(
    paths: Annotated[list[Path], typer.Argument(help="Scenario or family TOML files.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="The noise-floor JSON to write; the runs of these families "
                                      "replace theirs in it when it exists (scenarios/noise_floor.json: the one the "
                                      "regression checks read).")],
    draws: Annotated[int, typer.Option("--draws", min=0, max=50, help="Perturbed fusions a run, each with every "
                                       "input value multiplied by 1 + REL·N(0,1).")] = 5,
    rel: Annotated[float, typer.Option("--rel", min=0.0, max=1e-6, help="Relative size of the perturbation.")] = 1e-12,
    other_code_paths: Annotated[bool, typer.Option("--code-paths/--no-code-paths", help="Also fuse each run's own "
                                                   "inputs under other math-library code paths (GLIBC_TUNABLES, "
                                                   "NPY_DISABLE_CPU_FEATURES), each in a fresh process.")] = True,
    workers: Annotated[Optional[int], typer.Option("--workers", "-j", min=1,
                                                   help="Runs at a time (default: the CPU count).")] = None,
    param: Annotated[Optional[list[str]], typer.Option("--param", "-p", help="KEY=VALUE: an engine (FusionConfig) "
                                                       "parameter changed for every run, repeatable.")] = None,
) -> None:
    """The noise floor of scenario families: each run simulated once, then fused on its own inputs, on
    inputs perturbed at the last bits (seeded) and under other math-library code paths; per run the
    range of its Map-Fusion ATE. The regression checks of `pytest scenarios/` take their tolerances from
    it."""
    from sim.scenario import load_family

    import numpy as np

    from .noise import PERTURB_REL, code_paths, measure, measure_under, parse_params, summarise, with_engine_params

    _check_output_file(out, "--out", {str(p): p for p in paths})
    scenarios = _load_runs(paths)
    try:
        params = parse_params(param or [])
        scenarios = with_engine_params(scenarios, params) if params else scenarios
    except InputError as exc:
        _fail(str(exc))
    except ValueError as exc:
        _fail(f"--param {exc}")
    families = {sc.name: fam.name for p in paths for fam in [load_family(p)] for sc in fam.scenarios}
    n = workers or _default_workers()
    with _RunBar(len(scenarios), "runs") as bar:
        rows = measure(scenarios, draws=draws, rel=rel or PERTURB_REL, workers=n,
                       on_rows=lambda rs: bar.advance(any("error" in r for r in rs)))
    other: dict[str, list[dict]] = {}
    if other_code_paths:
        for name, env in code_paths().items():
            with err_console.status(f"fusing under the {name} code path ({', '.join(f'{k}={v}' for k, v in env.items())})"):
                other[name] = measure_under(env, paths, n, param or [])
    doc = summarise(rows, other, families, rel, draws)
    if out.exists():
        try:
            old = json.loads(out.read_text())
        except ValueError:
            _fail(f"--out {out}: not a noise-floor JSON file")
        doc["runs"] = dict(sorted({**old.get("runs", {}), **doc["runs"]}.items()))
    out.write_text(json.dumps(doc, indent=1) + "\n")
    t = Table(title=f"noise floor: Map-Fusion ATE over {draws} perturbed draws"
                    + (f" and {len(other)} code paths" if other else "") + f" → {out}")
    for c in ("family", "runs", "median spread", "max spread", "max range (m)", "de-localisation flips", "failed"):
        t.add_column(c, justify="right")
    by_family: dict[str, list[dict]] = {}
    for name in {r["scenario"] for r in rows}:
        by_family.setdefault(families.get(name, "?"), []).append(doc["runs"][name])
    for fam, es in sorted(by_family.items()):
        ok = [e for e in es if "spread" in e]
        sp = [e["spread"] for e in ok]
        t.add_row(fam, str(len(es)), f"{100 * float(np.median(sp)):.2f}%" if sp else "–",
                  f"{100 * max(sp):.2f}%" if sp else "–", f"{max(e['range_m'] for e in ok):.3f}" if ok else "–",
                  str(sum(e["delocalized_flips"] for e in ok)), str(len(es) - len(ok)))
    console.print(t)


@app.command()
def bench(
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object a line, `benchmark` names it.")] = False,
    duration_s: Annotated[float, typer.Option("--duration-s", min=60.0, help="Length of the engine's synthetic drive, "
                                              "seconds (10 Hz odometry).")] = 3600.0,
    city_km: Annotated[str, typer.Option("--city-km", help="Size of the synthetic city, WIDTHxHEIGHT km.")] = "10x15",
    repeats: Annotated[int, typer.Option("--repeats", min=1, max=20, help="Rounds of the engine and matcher "
                                         "benchmarks, each beside its anchor; medians are reported.")] = 3,
    config: Annotated[Optional[Path], typer.Option("--config", help="TOML with a [mapfusion] table: the engine's "
                                                   "configuration (default: the defaults).")] = None,
    map_name: Annotated[Optional[str], typer.Option("--map", help="A map to measure on (a built-in name such as "
                                                    "helsinki, or an OSM file) in place of the synthetic city; "
                                                    "--city-km is then not used.")] = None,
) -> None:
    """Throughput of the road-map build, the engine (with map priors, against a bare GTSAM chain measured
    in the same run: ratio_to_bare; ratio_to_bare_at_most: the most it could be with only GTSAM's updates and
    the road fixes' particles left in a frame) and the matcher (against a k-d tree ball query: *_ratio_to_kdtree)."""
    from .bench import run_benchmarks

    try:
        w, sep, h = city_km.lower().partition("x")
        size = (float(w), float(h))
        if not sep or not (0 < size[0] <= 10 and 0 < size[1] <= 15):
            raise ValueError
    except ValueError:
        _fail(f"--city-km {city_km!r}: expected WIDTHxHEIGHT in km, at most 10x15")
    from mapfusion.errors import MapFusionError
    from mapfusion.replay import load_fusion_config

    try:
        cfg = load_fusion_config(config)
    except MapFusionError as exc:
        _fail(str(exc))
    with err_console.status("benchmarking (road map, engine, matcher) ..."):
        try:
            for row in run_benchmarks(duration_s, size, repeats, cfg, map_name):
                if config is not None and row["benchmark"].startswith("engine"):
                    row = {**row, "config": str(config)}
                if as_json:
                    _print_json(row)
                else:
                    # (the rounds: in --json)
                    console.print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                           for k, v in row.items() if k != "rounds"), highlight=False)
        except MapFusionError as exc:  # (a missing map, or one that is not a map: the first thing the bench reads)
            _fail(str(exc))


def _finite_or_null(obj):
    """JSON has no Infinity or NaN: a non-finite float is printed as null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_null(v) for v in obj]
    return obj


def _print_json(obj, indent: int | None = None) -> None:
    """Strict JSON on stdout (``--json`` of every command)."""
    print(json.dumps(_finite_or_null(obj), indent=indent, allow_nan=False), flush=True)


def main(argv: list[str] | None = None) -> int:
    """Console-script entry point: the exit code (0 done, 1 an internal failure or a full disk, 2 bad input).

    Every refusal is one line on stderr: Typer's own usage errors (an unknown option, a bad value) are
    caught here and printed as one line rather than its boxed panel.
    """
    # click's exceptions, wherever this typer keeps them (recent typer vendors click)
    click_errors = sys.modules[typer.BadParameter.__module__]
    try:
        rv = app(args=argv, prog_name="mapfusion", standalone_mode=False)
        return rv if isinstance(rv, int) else 0
    except click_errors.NoArgsIsHelpError as exc:  # a bare group: its help, as --help would print
        print(exc.ctx.get_help())
        return 0
    except click_errors.UsageError as exc:
        where = f" (see 'mapfusion {exc.ctx.command_path.partition(' ')[2]} --help')".replace("  ", " ") if exc.ctx else ""
        _one_line(f"{exc.format_message()}{where}")
        return 2
    except click_errors.ClickException as exc:
        _one_line(exc.format_message())
        return exc.exit_code
    except typer.Abort:
        _one_line("aborted")
        return 1
    except InputError as exc:  # any bad input a command did not catch itself
        _one_line(str(exc))
        return 2
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            _one_line(f"{exc.strerror}{f' ({exc.filename})' if exc.filename else ''}: stopped; what finished is kept "
                      "and the same command resumes")
            return 1
        if exc.errno == errno.EPIPE:
            return 1
        raise


def _one_line(message: str) -> None:
    """The message on one line (rich markup escaped: messages name TOML tables such as [imu])."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(' '.join(message.split()))}", highlight=False, soft_wrap=True)


if __name__ == "__main__":
    sys.exit(main())
