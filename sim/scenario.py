"""Scenario and family files (DESIGN "Scenario files", contract).

A scenario is one drive, a TOML file whose every key has a documented default; an unknown key,
a wrong type or a value out of range is a :class:`ScenarioError` naming the key and the file. A
family is a base scenario, axes (a dotted key → list of values) and seeds, expanded to the
cartesian product; a plain scenario file is a family of one.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import itertools
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w

from mapfusion.config import FusionConfig, from_mapping, param, to_mapping
from mapfusion.errors import ConfigError, InputError
from mapfusion.formats import read_toml
from mapfusion.maps import resolve_map


class ScenarioError(ConfigError):
    """A scenario or family file is unusable (names the file and the key)."""


class DataUnavailableError(ScenarioError):
    """A path names an environment variable (``${MAPFUSION_DATA}/...``) that is not set: the run
    needs real data this machine has not been pointed at. Families list such runs as unavailable."""


_VAR = re.compile(r"\$\{(\w+)\}|\$(\w+)")


def expand_data_path(value: str, key: str, where: str) -> str:
    """``${VAR}`` / ``$VAR`` in a path replaced by the variable's value, made absolute (a relative
    value is relative to the working directory, as the shell that set it meant)."""
    if "$" not in value:
        return value

    def sub(m: re.Match) -> str:
        var = m.group(1) or m.group(2)
        val = os.environ.get(var)
        if not val:
            raise DataUnavailableError(f"{where}: {key} = {value!r} needs ${var}, which is not set "
                                       f"(point it at the real data, e.g. {var}=../shared/data)")
        return str(Path(val).expanduser().resolve())

    return _VAR.sub(sub, value)


class WeatherKind(str, enum.Enum):
    """Weather presets of the odometry error model."""

    clear = "clear"
    rain = "rain"
    heavy_rain = "heavy_rain"


class OdometryKind(str, enum.Enum):
    """The two odometry baselines of the paper, each alone or with the car's wheel speed and gyro."""

    vo = "vo"  # stereo visual odometry, fitted to a real frame-to-frame stereo VO on KITTI (issue 22)
    vio = "vio"  # stereo visual-inertial odometry, ORB-SLAM3-like
    mono = "mono"  # monocular visual odometry: arbitrary, drifting scale (fitted to a real one, issue 22)
    droid = "droid"  # the paper's VO: stereo DROID-SLAM, windowed bundle adjustment (fitted to its Table I)
    orb_vio = "orb-vio"  # the paper's VIO: stereo-inertial ORB-SLAM3 (fitted to its Table I); a map reset de-localises
    recorded = "recorded"  # a real odometry's output on a recorded drive ([odometry] file, KITTI format)
    vo_wheel = "vo+wheel"  # the vo, plus wheel speed ([wheel]) and the IMU's gyro into the engine (issue 18)
    vio_wheel = "vio+wheel"  # the vio, plus wheel speed and gyro

    @property
    def visual(self) -> OdometryKind:
        """The camera-based part (its preset): vo for vo+wheel, vio for vio+wheel."""
        return {OdometryKind.vo_wheel: OdometryKind.vo, OdometryKind.vio_wheel: OdometryKind.vio}.get(self, self)

    @property
    def resets_delocalise(self) -> bool:
        """Whether a map reset of the odometry counts as de-localisation, as the paper counts ORB-SLAM3's."""
        return self is OdometryKind.orb_vio

    @property
    def wheel(self) -> bool:
        """Whether wheel speed and gyro go into the engine (and wheel.csv into the run directory)."""
        return self in (OdometryKind.vo_wheel, OdometryKind.vio_wheel)


class Vehicle(str, enum.Enum):
    """Presets of the wheel-speed model (``[wheel] vehicle``)."""

    car = "car"
    truck = "truck"


class GpsMode(str, enum.Enum):
    """When GPS fixes are available to the engine."""

    init_only = "init_only"  # only during the initialisation window (KITTI, Oxford protocol)
    interval = "interval"  # one fix every interval_s (4Seasons, Singapore protocol)
    continuous = "continuous"  # at rate_hz throughout


class GpsSource(str, enum.Enum):
    """Where the fixes come from."""

    simulated = "simulated"  # the receiver model on the truth (σ, multipath outliers, denial)
    recorded = "recorded"  # the recorded drive's own fixes (a KITTI RTK track, a run's gps.csv)


@dataclass(frozen=True)
class TrafficConfig:
    """``[traffic]``: other vehicles sharing the road with the ego vehicle."""

    background_vehicles: int = param(0, "Other vehicles on random routes, so the ego slows and stops as in real traffic.",
                                     min=0, max=5000)
    fleet: bool = param(False, "Record every vehicle each step (fleet mode), not only the ego.")
    depart_spread_s: float = param(60.0, "Background vehicles depart uniformly over this many seconds.", unit="s", min=0.0,
                                   max=86400.0)


@dataclass(frozen=True)
class RouteConfig:
    """``[route]``: the ego's route. Empty ``edges`` draws a seeded random route of at least ``min_route_m``."""

    edges: tuple[str, ...] = param((), "SUMO edge ids the route passes, in order (joined by shortest paths).")
    max_trips: int = param(50, "Random trips chained at most to reach min_route_m.", min=1, max=1000)
    via_tunnel: bool = param(False, "The random route passes through an OSM tunnel (tunnel=yes / covered=yes), reached "
                             "after a random lead-in of tunnel_after_m; an error on a map without one.")
    tunnel_after_m: float = param(1500.0, "Random driving before the route heads for the tunnel (via_tunnel), so that "
                                  "GPS initialisation is over before it (about 1 km at town speeds).", unit="m", min=0.0,
                                  max=200000.0)


@dataclass(frozen=True)
class WeatherConfig:
    """``[weather]``."""

    kind: WeatherKind = param(WeatherKind.clear, "clear | rain | heavy_rain: presets of the odometry error model.")


@dataclass(frozen=True)
class GpsConfig:
    """``[gps]``: the GPS receiver."""

    mode: GpsMode = param(GpsMode.init_only, "init_only | interval | continuous.")
    source: GpsSource = param(GpsSource.simulated, "simulated | recorded: recorded takes the fixes of the recorded "
                              "drive named by `truth` (KITTI: the RTK track moved to camera 0), at the times mode, "
                              "rate_hz and interval_s select, declared with sigma_m; no noise or outliers are added.")
    interval_s: float = param(5.0, "Period of fixes in interval mode.", unit="s", min=0.0, exclusive_min=True,
                              max=86400.0, source="paper IV.B ('GPS every 5 seconds')")
    rate_hz: float = param(1.0, "Fix rate in continuous mode and during initialisation.", unit="Hz", min=0.0,
                           exclusive_min=True, max=100.0)
    sigma_m: float = param(2.0, "Horizontal σ of a fix (per axis).", unit="m", min=0.0, max=100.0)
    init_window_s: float = param(120.0, "Fixes at rate_hz for this long from the start (init_only: then none; "
                                 "interval: then one every interval_s). 120 s at city speeds pins the scale "
                                 "to about 0.1% with sigma_m = 2.", unit="s", min=0.0, max=86400.0)
    outlier_probability: float = param(0.01, "Probability that a fix is a multipath outlier.", min=0.0, max=1.0)
    outlier_sigma_m: float = param(30.0, "σ of a multipath outlier's error (per axis).", unit="m", min=0.0, max=10000.0)
    deny_in_tunnels: bool = param(True, "No fix on OSM tunnel=yes / covered roads, nor in the [[tunnels]] zones.")
    deny_under_bridges: bool = param(True, "No fix while passing under a bridge (another road above, layer > own).")
    bridge_lane_width_m: float = param(3.0, "Lane width of the bridges' roads: a frame is under a bridge within half "
                                       "its width (lanes × this) + 1 m.", unit="m", min=0.5, max=10.0,
                                       source="paper III.B's 3 m lane; the sensor model's own (issue 15: it read the "
                                       "engine's lane width)")


@dataclass(frozen=True)
class ImuParams:
    """``[imu]``: a consumer MEMS IMU (datasheet-class values of a smartphone / automotive-grade 6-axis part)."""

    rate_hz: float = param(100.0, "Sample rate.", unit="Hz", min=1.0, max=1000.0)
    accel_noise_density: float = param(2.0e-3, "Accelerometer white noise density.", unit="m/s²/√Hz", min=0.0, max=10.0)
    gyro_noise_density: float = param(2.0e-4, "Gyroscope white noise density (0.011 °/s/√Hz).", unit="rad/s/√Hz", min=0.0, max=1.0)
    accel_bias_sigma: float = param(0.05, "σ of the initial accelerometer bias, per axis.", unit="m/s²", min=0.0, max=10.0)
    gyro_bias_sigma: float = param(0.005, "σ of the initial gyroscope bias, per axis (0.3 °/s).", unit="rad/s", min=0.0, max=1.0)
    accel_bias_rw: float = param(5.0e-4, "Accelerometer bias random walk.", unit="m/s³/√Hz", min=0.0, max=1.0)
    gyro_bias_rw: float = param(2.0e-5, "Gyroscope bias random walk.", unit="rad/s²/√Hz", min=0.0, max=1.0)


@dataclass(frozen=True)
class TunnelZone:
    """``[[tunnels]]``: a GPS-denied, visually degraded zone by distance along the route."""

    start_m: float = param(0.0, "Start of the zone, distance along the route.", unit="m", min=0.0, max=1e6)
    end_m: float = param(0.0, "End of the zone, distance along the route.", unit="m", min=0.0, max=1e6)

    def __post_init__(self) -> None:
        if not self.end_m > self.start_m:
            raise ConfigError(f"tunnels: end_m ({self.end_m}) must be greater than start_m ({self.start_m})")


@dataclass(frozen=True)
class OdometryConfig:
    """``[odometry]``: the odometry kind; ``overrides`` (any other key of the table) replace
    fields of the kind × weather preset (see ``sim.sensors.OdometryParams``)."""

    kind: OdometryKind = param(OdometryKind.vo, "vo (stereo VO) | vio (stereo VIO) | mono (monocular VO) | droid, orb-vio (the "
                               "paper's DROID-SLAM and ORB-SLAM3 VIO) | vo+wheel | "
                               "vio+wheel (the same with the car's wheel speed and gyro fused: [wheel]) | recorded "
                               "(a real odometry's output, with file).")
    overrides: tuple[tuple[str, float], ...] = param((), "Preset fields replaced by the scenario.")
    file: str = param("", "kind = recorded: the odometry's poses in KITTI's format (12 numbers a line, camera frame: "
                      "x right, y down, z forward), one line per frame of the recorded drive (truth = a KITTI "
                      "directory); may name ${MAPFUSION_DATA}.")


class KidnapKind(str, enum.Enum):
    """How a ``kidnapped`` drive knocks the estimate off (issue 17)."""

    none = "none"
    gps_bias = "gps_bias"  # every fix carries one bias: the engine initialises in the wrong place
    vo_jump = "vo_jump"  # the VO loses track for gap_s and re-initialises with a pose jump and a heading error


@dataclass(frozen=True)
class KidnapConfig:
    """``[kidnap]``: the estimate knocked off after initialisation (issue 17). The magnitudes are drawn from
    the scenario's seed (a fifth sensor stream: the others are unchanged) within the ranges below; the drawn
    values are written to ``sensor_events.json``."""

    kind: KidnapKind = param(KidnapKind.none, "none | gps_bias | vo_jump.")
    bias_min_m: float = param(50.0, "gps_bias: smallest bias of the fixes.", unit="m", min=0.0, max=100000.0,
                              source="issue 17")
    bias_max_m: float = param(200.0, "gps_bias: largest bias.", unit="m", min=0.0, max=100000.0, source="issue 17")
    jump_min_m: float = param(30.0, "vo_jump: smallest pose jump at the re-initialisation.", unit="m", min=0.0,
                              max=100000.0, source="issue 17")
    jump_max_m: float = param(300.0, "vo_jump: largest pose jump.", unit="m", min=0.0, max=100000.0,
                              source="issue 17")
    heading_max_deg: float = param(30.0, "vo_jump: largest heading error at the re-initialisation (either sign).",
                                   unit="deg", min=0.0, max=180.0, source="issue 17")
    at_min_m: float = param(100.0, "vo_jump: earliest start of the outage, in metres driven after the last GPS "
                            "fix.", unit="m", min=0.0, max=1000000.0, source="issue 17: after initialisation")
    at_max_m: float = param(500.0, "vo_jump: latest start of the outage after the last fix (a drive that ends "
                            "sooner has no kidnap).", unit="m", min=0.0, max=1000000.0)
    gap_s: float = param(8.0, "vo_jump: the VO's outage before it re-initialises (no frames): long enough that "
                         "the jump is not an impossible speed.", unit="s", min=0.0, max=3600.0)


@dataclass(frozen=True)
class WheelConfig:
    """``[wheel]``: the wheel-speed sensor of odometry kinds vo+wheel and vio+wheel; ``overrides`` (any
    other key of the table) replace fields of the vehicle's preset (see ``sim.sensors.WheelParams``)."""

    vehicle: Vehicle = param(Vehicle.car, "car | truck: the preset of the wheel-speed model.")
    overrides: tuple[tuple[str, float], ...] = param((), "Preset fields replaced by the scenario.")


#: An estimator's name: the infix of its result keys (``ate_<name>_m``) and of ``estimate_<name>.tum``.
ESTIMATOR_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")
#: The names the test bed's own two estimates use.
RESERVED_ESTIMATORS = ("odometry", "mapfusion", "reduction")


@dataclass(frozen=True)
class EstimatorSpec:
    """``[[estimators]]``: a method scored beside the odometry and Map-Fusion on the same inputs
    (``mapfusion.harness.estimators``). Exactly one of ``use`` and ``command``."""

    name: str = param("", "Its name in tables and result keys (ate_<name>_m): lower-case letters, digits and '_', "
                      "at most 32, not odometry or mapfusion.")
    use: str = param("", "A Python class, module:Class or the name of a mapfusion.estimators entry point; made as "
                     "Class(road, **params) and fed the run's inputs in time order.")
    command: str = param("", "An external command instead, run once per run: a template whose {odometry}, {gps}, "
                         "{imu}, {wheel}, {map} and {out} become file paths; it reads the inputs and writes a TUM "
                         "estimate to {out}.")
    params: tuple[tuple[str, Any], ...] = param((), "Keyword arguments of the class (an inline table).")
    timeout_s: float = param(3600.0, "An estimator still running after this long fails its column.", unit="s",
                             min=0.0, exclusive_min=True, max=86400.0)


@dataclass(frozen=True)
class Scenario:
    """One drive: map, seed, timing, traffic, weather, sensors, GPS-denied zones and engine parameters."""

    name: str = param("scenario", "Name of the run (its directory under --out, and in tables): one path component "
                      "of letters, digits, '_', '.', '+', '-', at most 128, not starting with '.', '+' or '-'.")
    map: str = param("helsinki", "OSM file: built-in name, path relative to the scenario file, or absolute.")
    seed: int = param(1, "Seed of everything random in the run (route, traffic, sensors).", min=0, max=2**31 - 1)
    duration_s: float = param(600.0, "Upper bound on simulated time.", unit="s", min=0.0, exclusive_min=True, max=86400.0)
    step_s: float = param(0.1, "SUMO step = odometry frame period.", unit="s", min=0.01, max=1.0)
    min_route_m: float = param(1500.0, "Minimum length of a random route.", unit="m", min=0.0, max=200000.0)
    truth: str = param("", "A recorded drive instead of a SUMO drive: a KITTI sequence directory (poses.txt, "
                       "times.txt, rtk_gps.kml; its map.osm is the default map), or a TUM trajectory in the map's "
                       "ENU frame (a gps.csv beside it is its recorded GPS). Relative to the file; ${VAR} expands. "
                       "Empty: SUMO drives.")
    traffic: TrafficConfig = param(TrafficConfig(), "[traffic]")
    route: RouteConfig = param(RouteConfig(), "[route]")
    weather: WeatherConfig = param(WeatherConfig(), "[weather]")
    odometry: OdometryConfig = param(OdometryConfig(), "[odometry]")
    gps: GpsConfig = param(GpsConfig(), "[gps]")
    imu: ImuParams = param(ImuParams(), "[imu]")
    wheel: WheelConfig = param(WheelConfig(), "[wheel] (odometry kinds with +wheel only)")
    tunnels: tuple[TunnelZone, ...] = param((), "[[tunnels]]")
    kidnap: KidnapConfig = param(KidnapConfig(), "[kidnap] (issue 17)")
    mapfusion: FusionConfig = param(FusionConfig(), "[mapfusion]")
    estimators: tuple[EstimatorSpec, ...] = param((), "[[estimators]]: methods scored beside Map-Fusion")

    def to_toml_dict(self) -> dict:
        """The fully resolved scenario as a TOML-ready mapping (``scenario.toml`` of a run)."""
        d = to_mapping(self)
        odo = d.pop("odometry")
        d["odometry"] = {"kind": odo["kind"], **({"file": odo["file"]} if odo.get("file") else {}),
                         **{k: v for k, v in odo.get("overrides", [])}}
        wheel = d.pop("wheel")
        if self.odometry.kind.wheel:  # written only where the scenario has a wheel sensor
            d["wheel"] = {"vehicle": wheel["vehicle"], **{k: v for k, v in wheel.get("overrides", [])}}
        if self.kidnap.kind is KidnapKind.none:  # (a drive without a kidnap writes no table: unchanged files)
            del d["kidnap"]
        d["tunnels"] = [to_mapping(z) for z in self.tunnels]
        if not d["tunnels"]:
            del d["tunnels"]
        del d["estimators"]
        if self.estimators:  # (a scenario without them writes no table: unchanged files)
            d["estimators"] = [_estimator_toml(e) for e in self.estimators]
        return d

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_toml_dict())

    def content_hash(self) -> str:
        """SHA-256 of the fully resolved scenario (engine configuration included): what a resumed
        ``run`` or ``sweep`` compares, so that an edited scenario is run again, not reported stale."""
        import hashlib

        return hashlib.sha256(self.to_toml().encode()).hexdigest()

    def replace(self, **changes) -> Scenario:
        return dataclasses.replace(self, **changes)


_SECTIONS = {"traffic": TrafficConfig, "route": RouteConfig, "weather": WeatherConfig, "gps": GpsConfig,
             "imu": ImuParams, "kidnap": KidnapConfig, "mapfusion": FusionConfig}


#: A run's name becomes its directory under --out: one safe path component, never "..", "/x" or "".
_RUN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}")


def scenario_from_dict(data: dict, where: str, base_dir: Path | None = None, resolve: bool = True) -> Scenario:
    """A :class:`Scenario` from a TOML mapping; ``where`` names the source in errors.

    With ``resolve`` the map is resolved now (built-in name, relative to ``base_dir``, or absolute),
    so a missing map is reported before any simulation starts. Raises :class:`ScenarioError`.
    """
    try:
        return _scenario_from_dict(data, where, base_dir, resolve)
    except ScenarioError:
        raise
    except ConfigError as exc:
        raise ScenarioError(str(exc)) from None


def _scenario_from_dict(data: dict, where: str, base_dir: Path | None, resolve: bool) -> Scenario:
    data = copy.deepcopy(data)
    top_fields = {f.name for f in dataclasses.fields(Scenario)}
    unknown = sorted(set(data) - top_fields)
    if unknown:
        raise ScenarioError(f"{where}: unknown key {unknown[0]} (known: {', '.join(sorted(top_fields))})")
    kwargs: dict[str, Any] = {}
    for key, cls in _SECTIONS.items():
        if key in data:
            kwargs[key] = from_mapping(cls, data.pop(key), where, prefix=f"{key}.")
    if "odometry" in data:
        odo = data.pop("odometry")
        if not isinstance(odo, dict):
            raise ScenarioError(f"{where}: [odometry] must be a table")
        kind = odo.pop("kind", OdometryKind.vo.value)
        file = odo.pop("file", "")
        base = from_mapping(OdometryConfig, {"kind": kind, "file": file}, where, prefix="odometry.")
        kwargs["odometry"] = dataclasses.replace(base, overrides=_preset_overrides(odo, where, "odometry"))
    if "wheel" in data:
        wheel = data.pop("wheel")
        if not isinstance(wheel, dict):
            raise ScenarioError(f"{where}: [wheel] must be a table")
        base_w = from_mapping(WheelConfig, {"vehicle": wheel.pop("vehicle", Vehicle.car.value)}, where, prefix="wheel.")
        kwargs["wheel"] = dataclasses.replace(base_w, overrides=_preset_overrides(wheel, where, "wheel"))
        from .sensors import wheel_preset

        w = wheel_preset(kwargs["wheel"].vehicle).with_overrides(kwargs["wheel"].overrides)
        if w.scale_error_max < w.scale_error_min:
            raise ScenarioError(f"{where}: wheel.scale_error_max ({w.scale_error_max:g}) is below wheel.scale_error_min "
                                f"({w.scale_error_min:g})")
    if "tunnels" in data:
        zones = data.pop("tunnels")
        if not isinstance(zones, list):
            raise ScenarioError(f"{where}: tunnels must be an array of tables ([[tunnels]])")
        kwargs["tunnels"] = tuple(from_mapping(TunnelZone, z, where, prefix=f"tunnels[{i}].") for i, z in enumerate(zones))
    if "estimators" in data:
        kwargs["estimators"] = _estimators(data.pop("estimators"), where)
    map_given = "map" in data
    top = from_mapping(Scenario, data, where) if data else Scenario()
    sc = dataclasses.replace(top, **kwargs)
    if not _RUN_NAME.fullmatch(sc.name):
        raise ScenarioError(f"{where}: name {sc.name!r} must be one path component of at most 128 letters, digits, "
                            "'_', '.', '+' or '-', not starting with '.', '+' or '-' (it names the run's directory)")
    k = sc.kidnap
    if k.bias_max_m < k.bias_min_m or k.jump_max_m < k.jump_min_m or k.at_max_m < k.at_min_m:
        raise ScenarioError(f"{where}: kidnap: a *_max below its *_min")
    if sc.gps.source is GpsSource.recorded and not sc.truth:
        raise ScenarioError(f"{where}: gps.source = \"recorded\" needs a recorded drive (truth = ...)")
    recorded_odometry = sc.odometry.kind is OdometryKind.recorded
    if recorded_odometry != bool(sc.odometry.file):
        raise ScenarioError(f"{where}: odometry.file goes with odometry.kind = \"recorded\", and the kind needs the file")
    if recorded_odometry and (not sc.truth or sc.odometry.overrides):
        raise ScenarioError(f"{where}: odometry.kind = \"recorded\" needs a recorded drive (truth = a KITTI directory) "
                            "and takes no preset fields")
    if not resolve:
        return sc
    if recorded_odometry:
        f = Path(expand_data_path(sc.odometry.file, "odometry.file", where)).expanduser()
        if not f.is_absolute() and base_dir is not None:
            f = base_dir / f
        if not f.is_file():
            raise ScenarioError(f"{where}: odometry.file: {f}: no such file")
        sc = dataclasses.replace(sc, odometry=dataclasses.replace(sc.odometry, file=str(f.resolve())))
    if sc.truth:
        truth = Path(expand_data_path(sc.truth, "truth", where)).expanduser()
        if not truth.is_absolute() and base_dir is not None:
            truth = base_dir / truth
        if not truth.exists():
            raise ScenarioError(f"{where}: truth: {truth}: no such file or directory")
        if truth.is_dir():
            missing = [f for f in KITTI_FILES if not (truth / f).exists()]
            if missing:
                raise ScenarioError(f"{where}: truth: {truth} is a directory but not a KITTI sequence "
                                    f"(missing {', '.join(missing)})")
            if not map_given:
                sc = dataclasses.replace(sc, map=str(truth / "map.osm"))
        sc = dataclasses.replace(sc, truth=str(truth.resolve()))
    try:
        mp = expand_data_path(sc.map, "map", where)
        sc = dataclasses.replace(sc, map=str(resolve_map(mp, base_dir).resolve()))
    except DataUnavailableError:
        raise
    except InputError as exc:
        raise ScenarioError(f"{where}: map: {exc}") from None
    return sc


#: The files an external estimator's command may name: {odometry} (TUM, the odometry's own frame), {gps} (CSV
#: t,lat,lon,alt,sigma_m), {imu} and {wheel} (CSV, where the run feeds them; else empty files), {map} (the OSM
#: file) and {out} (the TUM estimate it writes, in the map's ENU frame).
COMMAND_FILES = ("odometry", "gps", "imu", "wheel", "map", "out")


def command_arguments(template: str, files: dict[str, str]) -> list[str]:
    """The command's argument list: the template split as a shell would (no shell runs it), each {name} in an
    argument replaced by ``files[name]``. A ValueError for an unknown {name}, a template without {out}, an
    unbalanced quote or brace, or an empty command."""
    import shlex
    import string

    try:
        words = shlex.split(template)
    except ValueError as exc:
        raise ValueError(f"{template!r}: {exc}") from None
    if not words:
        raise ValueError("an empty command")
    named: set[str] = set()
    out = []
    for w in words:
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(w) if f is not None]
        except ValueError as exc:
            raise ValueError(f"{w!r}: {exc} (a literal brace is written {{{{ or }}}})") from None
        for f in fields:
            if f not in COMMAND_FILES:
                raise ValueError(f"{{{f}}} is not one of {', '.join('{' + k + '}' for k in COMMAND_FILES)}")
        named.update(fields)
        out.append(w.format(**files))
    if "out" not in named:
        raise ValueError("the command must name {out}, the TUM estimate it writes")
    return out


def _estimator_toml(e: EstimatorSpec) -> dict:
    d: dict[str, Any] = {"name": e.name}
    d.update({"use": e.use} if e.use else {"command": e.command})
    if e.params:
        d["params"] = dict(e.params)
    d["timeout_s"] = e.timeout_s
    return d


def _estimators(tables: Any, where: str) -> tuple[EstimatorSpec, ...]:
    """``[[estimators]]``, checked before any run: names, one of use / command, the command's placeholders."""
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ScenarioError(f"{where}: estimators must be an array of tables ([[estimators]])")
    out: list[EstimatorSpec] = []
    for i, t in enumerate(tables):
        t = dict(t)
        at = f"estimators[{i}]"
        params = t.pop("params", {})
        if not isinstance(params, dict):
            raise ScenarioError(f"{where}: {at}.params must be a table (params = {{ key = value }})")
        e = from_mapping(EstimatorSpec, t, where, prefix=f"{at}.")
        e = dataclasses.replace(e, params=tuple(params.items()))
        if not ESTIMATOR_NAME.fullmatch(e.name) or e.name in RESERVED_ESTIMATORS:
            raise ScenarioError(f"{where}: {at}.name {e.name!r} must be 1-32 lower-case letters, digits or '_', "
                                f"starting with a letter, and not {', '.join(RESERVED_ESTIMATORS)}")
        if e.name in {o.name for o in out}:
            raise ScenarioError(f"{where}: {at}.name {e.name!r}: two estimators of that name")
        if bool(e.use) == bool(e.command):
            raise ScenarioError(f"{where}: {at} ({e.name}): give use (a Python class) or command (an external "
                                "program), one of them")
        if e.command:
            try:
                command_arguments(e.command, {k: k for k in COMMAND_FILES})
            except ValueError as exc:
                raise ScenarioError(f"{where}: {at}.command: {exc}") from None
        if e.params and not e.use:
            raise ScenarioError(f"{where}: {at}.params go with use (a Python class); a command takes its own "
                                "arguments")
        out.append(e)
    return tuple(out)


#: What a KITTI sequence directory holds (shared/data/README.md); map.osm is optional.
KITTI_FILES = ("poses.txt", "times.txt", "rtk_gps.kml")


def _preset_overrides(table: dict, where: str, section: str) -> tuple[tuple[str, float], ...]:
    """The preset fields an ``[odometry]`` or ``[wheel]`` table replaces, each checked against its
    documented range."""
    from .sensors import OdometryParams, WheelParams

    cls = OdometryParams if section == "odometry" else WheelParams
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ScenarioError(f"{where}: unknown key {section}.{unknown[0]} (preset fields: {', '.join(sorted(known))})")
    checked = from_mapping(cls, table, where, prefix=f"{section}.")
    return tuple((k, float(getattr(checked, k))) for k in sorted(table))


def _read_toml(path: Path) -> dict:
    return read_toml(path, "scenario file", ScenarioError)


def load_scenario(path: str | Path) -> Scenario:
    """One scenario file (not a family)."""
    p = Path(path)
    data = _read_toml(p)
    if "family" in data:
        raise ScenarioError(f"{p}: is a family file; use load_family")
    return scenario_from_dict(data, str(p), p.parent)


@dataclass(frozen=True)
class Family:
    """A named set of scenarios (the expansion of base × axes × seeds)."""

    name: str
    scenarios: tuple[Scenario, ...]
    source: str
    #: (run name, reason) of runs left out because their real data is not available here
    #: (an unset ``${MAPFUSION_DATA}``); every other problem is an error.
    unavailable: tuple[tuple[str, str], ...] = ()


def _set_dotted(d: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    for p in parts[:-1]:
        d = d.setdefault(p, {})
        if not isinstance(d, dict):
            raise ScenarioError(f"axis {dotted}: {p} is not a table")
    d[parts[-1]] = value


def _slug(v: Any) -> str:
    if isinstance(v, (list, tuple)):  # a list of tables ([[tunnels]] zones): their values, or "none"
        return "-".join(_slug(x) for x in v) or "none"
    if isinstance(v, dict):
        return "-".join(_slug(x) for x in v.values())
    if isinstance(v, str) and v.startswith("$"):  # ${MAPFUSION_DATA}/osm/andorra.osm.pbf → andorra
        name = Path(v).name
        for ext in (".osm.pbf", ".osm.gz", ".osm.bz2", ".osm", ".pbf", ".tum", ".txt"):
            name = name.removesuffix(ext)
        return name
    return str(v).replace("/", "-").replace(" ", "").replace(".osm.pbf", "").replace(".osm", "")


def expand_family(data: dict, where: str, base_dir: Path | None = None) -> Family:
    """Expand a family mapping ([family] name, seeds, axes; [base]) into its scenarios."""
    fam = data.get("family")
    if not isinstance(fam, dict):
        raise ScenarioError(f"{where}: [family] must be a table")
    unknown = sorted(set(data) - {"family", "base"})
    if unknown:
        raise ScenarioError(f"{where}: unknown key {unknown[0]} in a family file (known: family, base)")
    unknown = sorted(set(fam) - {"name", "seeds", "axes", "zip"})
    if unknown:
        raise ScenarioError(f"{where}: unknown key family.{unknown[0]} (known: name, seeds, axes, zip)")
    name = fam.get("name")
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{where}: family.name must be a non-empty string")
    seeds = fam.get("seeds", [1])
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds):
        raise ScenarioError(f"{where}: family.seeds must be a non-empty list of whole numbers ≥ 0")
    axes = fam.get("axes", {})
    if not isinstance(axes, dict) or not all(isinstance(v, list) and v for v in axes.values()):
        raise ScenarioError(f"{where}: family.axes must map dotted keys to non-empty lists")
    zipped = fam.get("zip", {})
    if not isinstance(zipped, dict) or not all(isinstance(v, list) and v for v in zipped.values()):
        raise ScenarioError(f"{where}: family.zip must map dotted keys to non-empty lists")
    if len({len(v) for v in zipped.values()}) > 1:
        raise ScenarioError(f"{where}: family.zip: every list must have the same length (they vary together)")
    if set(zipped) & set(axes):
        raise ScenarioError(f"{where}: {sorted(set(zipped) & set(axes))[0]} is both in family.axes and family.zip")
    base = data.get("base", {})
    if not isinstance(base, dict):
        raise ScenarioError(f"{where}: [base] must be a table")
    # the zipped keys form one axis whose values are tuples (one run per position)
    zkeys = list(zipped)
    axes = dict(axes)
    if zkeys:
        axes["\0zip"] = list(zip(*(zipped[k] for k in zkeys)))
    keys = list(axes)
    scenarios = []
    unavailable = []
    seen = set()
    for combo in itertools.product(*(axes[k] for k in keys)):
        for seed in seeds:
            d = copy.deepcopy(base)
            parts = [name]
            for k, v in zip(keys, combo):
                if k == "\0zip":
                    for zk, zv in zip(zkeys, v):
                        _set_dotted(d, zk, zv)
                    parts += [_slug(zv) for zv in v]
                else:
                    _set_dotted(d, k, v)
                    parts.append(_slug(v))
            d["seed"] = seed
            parts.append(f"s{seed}")
            d["name"] = "-".join(parts)
            if d["name"] in seen:
                raise ScenarioError(f"{where}: two runs would be named {d['name']}")
            seen.add(d["name"])
            try:
                scenarios.append(scenario_from_dict(d, f"{where} ({d['name']})", base_dir))
            except DataUnavailableError as exc:
                unavailable.append((d["name"], str(exc)))
    if not scenarios and not unavailable:
        raise ScenarioError(f"{where}: the family has no runs")
    return Family(name=name, scenarios=tuple(scenarios), source=where, unavailable=tuple(unavailable))


def load_family(path: str | Path) -> Family:
    """A family file, or a scenario file as a family of one."""
    p = Path(path)
    data = _read_toml(p)
    if "family" not in data:
        sc = scenario_from_dict(data, str(p), p.parent)
        return Family(name=sc.name, scenarios=(sc,), source=str(p))
    return expand_family(data, str(p), p.parent)
