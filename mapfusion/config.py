"""Configuration: frozen dataclasses with documented defaults, strictly loaded from TOML tables.

:func:`from_mapping` is the one loader: an unknown key, a wrong type or a value out of range is
a :class:`~mapfusion.errors.ConfigError` naming the key and where it came from. Field metadata
carries the documentation (``doc``), the unit and the allowed range (``min``/``max``, with
``exclusive_min``), so the loader, the docs and the CLI agree.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from .errors import ConfigError


def param(
    default: Any,
    doc: str,
    *,
    unit: str = "",
    min: float | None = None,
    max: float | None = None,
    exclusive_min: bool = False,
    source: str = "",
) -> Any:
    """A dataclass field with documentation, unit, range and source."""
    return field(
        default=default,
        metadata={"doc": doc, "unit": unit, "min": min, "max": max, "exclusive_min": exclusive_min, "source": source},
    )


_ENUM_FIELDS: dict[type, tuple[tuple[str, type], ...]] = {}


def _enum_fields(cls: type) -> tuple[tuple[str, type], ...]:
    """(name, Enum class) of every field of the dataclass ``cls`` whose type is an Enum (worked out once)."""
    if cls not in _ENUM_FIELDS:
        hints = typing.get_type_hints(cls)
        _ENUM_FIELDS[cls] = tuple((f.name, hints[f.name]) for f in dataclasses.fields(cls)
                                  if isinstance(hints[f.name], type) and issubclass(hints[f.name], enum.Enum))
    return _ENUM_FIELDS[cls]


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str, where: str) -> Any:
    """Check (and lightly convert: int → float, list → tuple, str → Enum) one value."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(value, args[0], key, where)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(value)
        except ValueError:
            choices = ", ".join(str(m.value) for m in tp)
            raise ConfigError(f"{where}: {key} = {value!r} is not one of {choices}") from None
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: {key} must be a whole number, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: {key} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: {key} must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: {key} must be a string, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: {key} must be a list, got {value!r}")
        targs = typing.get_args(tp)
        item_tp = targs[0] if targs else Any
        return tuple(_convert(v, item_tp, f"{key}[{i}]", where) for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: [{key}] must be a table, got {value!r}")
        return from_mapping(typing.cast(type, tp), value, where, prefix=f"{key}.")
    if tp is Any:
        return value
    raise ConfigError(f"{where}: {key}: unsupported type {_type_name(tp)}")


#: A number field with no documented maximum still has this one: no quantity of the engine or the
#: simulation is meaningful beyond 10⁹ of its unit, and 1e308 would overflow the arithmetic after it.
GENERIC_MAX = 1.0e9


def _check_range(f: dataclasses.Field, value: Any, key: str, where: str) -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return
    lo, hi = f.metadata.get("min"), f.metadata.get("max")
    if hi is None and isinstance(value, float):
        hi = GENERIC_MAX
    unit = f.metadata.get("unit") or ""
    if lo is not None:
        if f.metadata.get("exclusive_min") and not value > lo:
            raise ConfigError(f"{where}: {key} must be > {lo:g}{' ' + unit if unit else ''}, got {value!r}")
        if not value >= lo:
            raise ConfigError(f"{where}: {key} must be ≥ {lo:g}{' ' + unit if unit else ''}, got {value!r}")
    if hi is not None and not value <= hi:
        raise ConfigError(f"{where}: {key} must be ≤ {hi:g}{' ' + unit if unit else ''}, got {value!r}")


def from_mapping(cls: type, data: dict, where: str = "config", prefix: str = ""):
    """Build the frozen dataclass ``cls`` from a TOML table, strictly.

    ``where`` names the source (a file) in error messages; ``prefix`` the table (``gps.``).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: [{prefix.rstrip('.')}] must be a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    retired: dict[str, str] = getattr(cls, "RETIRED_KEYS", {})
    for key in sorted(set(data) & set(retired)):
        raise ConfigError(f"{where}: {prefix}{key} {retired[key]}")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {prefix}{unknown[0]!s} (known in this table: {', '.join(sorted(fields))})"
        )
    kwargs = {}
    for name, value in data.items():
        f = fields[name]
        v = _convert(value, hints[name], prefix + name, where)
        _check_range(f, v, prefix + name, where)
        kwargs[name] = v
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def to_mapping(obj) -> dict:
    """A frozen config dataclass as plain TOML-ready values (Enums by value, tuples as lists, no None)."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if v is None:
            continue
        out[f.name] = _plain(v)
    return out


def _plain(v):
    if dataclasses.is_dataclass(v):
        return to_mapping(v)
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items() if x is not None}
    if isinstance(v, Path):
        return str(v)
    return v


def describe(cls: type) -> list[tuple[str, str, Any, str, str]]:
    """(name, type, default, unit, doc) of every field: for docs and ``--help`` texts."""
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else None
        rows.append(
            (f.name, _type_name(hints[f.name]), _plain(default), f.metadata.get("unit", ""), f.metadata.get("doc", ""))
        )
    return rows


# ----------------------------------------------------------------------------- engine configuration
class Backend(str, enum.Enum):
    """Factor-graph backends (DESIGN item 6)."""

    fixed_lag = "fixed_lag"  # bounded cost per frame: the default for long drives
    isam2 = "isam2"  # ISAM2 over the whole history, as the paper


class ScaleFormula(str, enum.Enum):
    """How the odometry scale is estimated from GPS (DESIGN item 4)."""

    speed_ratio = "speed_ratio"  # (‖d_gps‖/t_gps) / (‖d_vo‖/t_vo): the default
    paper = "paper"  # the paper's printed S = ‖d_gps‖²/‖d_vo‖² · t_vo/t_gps


class StateModel(str, enum.Enum):
    """How the vehicle state is constrained (DESIGN item 7)."""

    planar = "planar"  # ground vehicle: odometry projected on the horizontal plane, z/roll/pitch held level
    pose3 = "pose3"  # the paper's free Pose3: z, roll and pitch left to the optimiser


class OutageStep(str, enum.Enum):
    """What the engine takes as the motion across an odometry gap longer than ``reloc_gap_s`` (the VO lost track)."""

    odometry = "odometry"  # the odometry's own step across it (a re-initialised VO's guess)
    constant_velocity = "constant_velocity"  # the last plausible step's velocity, straight on, over the gap
    road = "road"  # that distance along the road graph from the matched road (with the map; else constant_velocity)


class PriorMode(str, enum.Enum):
    """Which directions the map prior constrains (DESIGN items 3 and 7)."""

    paper = "paper"  # x/y covariance from Σ = EΛE⁻¹ with λ1 = |v_lon|, λ2 = |v_lat| (floored)
    along_free = "along_free"  # the same across the road, zero precision along it


class PriorTarget(str, enum.Enum):
    """Where the map prior puts the vehicle across its road (issue 16)."""

    centre = "centre"  # on the centre line (paper III.B)
    edge = "edge"  # on the nearest edge of the band |lateral| ≤ road width, with the paper's σ
    band = "band"  # the band |lateral| ≤ road width, combined with the estimate's own σ


class RobustKernel(str, enum.Enum):
    """M-estimator on the map prior, so that a wrong match cannot drag the estimate."""

    none = "none"
    huber = "huber"
    cauchy = "cauchy"


class Factorization(str, enum.Enum):
    """Linear solver of ISAM2 (DESIGN item 7: Cholesky failed where QR did not)."""

    qr = "QR"
    cholesky = "CHOLESKY"


#: Settings that became fixed values of the part that uses them (name = value), each documented there.
_FIXED_KEYS: dict[str, str] = {
    "max_odometry_speed_mps": "mapfusion.track.MAX_ODOMETRY_SPEED_MPS = 70.0 m/s",
    "level_window_s": "mapfusion.track.LEVEL_WINDOW_S = 60.0 s",
    "outage_s": "mapfusion.track.OUTAGE_S = 1.0 s",
    "prior_band_fraction": "mapfusion.association.PRIOR_BAND_FRACTION = 1.0",
    "heading_prior_max_deg": "mapfusion.association.HEADING_PRIOR_MAX_DEG = 10.0 deg",
    "relocalise_track_speed_mps": "mapfusion.gps_gate.RELOCALISE_TRACK_SPEED_MPS = 70.0 m/s",
    "gps_max_frame_gap_s": "mapfusion.gps_gate.GPS_MAX_FRAME_GAP_S = 1.0 s",
    "relocalise_window_s": "mapfusion.gps_gate.RELOCALISE_WINDOW_S = 60.0 s",
    "relocalise_min_baseline_m": "mapfusion.gps_gate.RELOCALISE_MIN_BASELINE_M = 5.0 m",
    "relocalise_yaw_sigma_floor_deg": "mapfusion.gps_gate.RELOCALISE_YAW_SIGMA_FLOOR_DEG = 2.0 deg",
    "relocalise_distance_tolerance": "mapfusion.gps_gate.RELOCALISE_DISTANCE_TOLERANCE = 0.05",
    "odometry_prior_every_s": "mapfusion.estimate.ODOMETRY_PRIOR_EVERY_S = 1.0 s",
    "update_every": "mapfusion.estimate.UPDATE_EVERY = 5",
    "relinearize_threshold": "mapfusion.smoother.RELINEARIZE_THRESHOLD = 0.01",
    "reanchor_yaw_sigma_deg": "mapfusion.smoother.REANCHOR_YAW_SIGMA_DEG = 2.0 deg",
    "reanchor_sigma_m": "mapfusion.smoother.REANCHOR_SIGMA_M = 0.5 m",
    "init_min_fixes": "mapfusion.initialisation.INIT_MIN_FIXES = 3",
    "init_stall_min_samples": "mapfusion.initialisation.INIT_STALL_MIN_SAMPLES = 5",
    "init_prior_yaw_sigma_deg": "mapfusion.initialisation.INIT_PRIOR_YAW_SIGMA_DEG = 10.0 deg",
    "init_prior_sigma_m": "mapfusion.initialisation.INIT_PRIOR_SIGMA_M = 5.0 m",
    "init_prior_tilt_sigma_deg": "mapfusion.initialisation.INIT_PRIOR_TILT_SIGMA_DEG = 2.0 deg",
    "init_prior_z_sigma_m": "mapfusion.initialisation.INIT_PRIOR_Z_SIGMA_M = 1.0 m",
    "scale_outlier_sigma": "mapfusion.initialisation.SCALE_OUTLIER_SIGMA = 4.0",
    "scale_outlier_floor_m": "mapfusion.initialisation.SCALE_OUTLIER_FLOOR_M = 3.0 m",
    "scale_fit_min_extent_m": "mapfusion.initialisation.SCALE_FIT_MIN_EXTENT_M = 50.0 m",
    "scale_refit_window_s": "mapfusion.initialisation.SCALE_REFIT_WINDOW_S = 300.0 s",
    "scale_fit_min_fixes": "mapfusion.odometry_trust.SCALE_FIT_MIN_FIXES = 10",
    "scale_fit_outlier_sigma": "mapfusion.odometry_trust.SCALE_FIT_OUTLIER_SIGMA = 3.0",
    "scale_fit_outlier_floor_m": "mapfusion.odometry_trust.SCALE_FIT_OUTLIER_FLOOR_M = 1.0 m",
    "outage_on_road_deg": "mapfusion.reanchoring.OUTAGE_ON_ROAD_DEG = 10.0 deg",
    "outage_end_max_deg": "mapfusion.reanchoring.OUTAGE_END_MAX_DEG = 45.0 deg",
    "outage_rot_sigma_deg": "mapfusion.factors.OUTAGE_ROT_SIGMA_DEG = 20.0 deg",
    "wheel_frame_gap_s": "mapfusion.motion.WHEEL_FRAME_GAP_S = 0.3 s",
    "wheel_scale_window_s": "mapfusion.motion.WHEEL_SCALE_WINDOW_S = 300.0 s",
    "reloc_seed": "mapfusion.relocalise.RELOC_SEED = 0",
    "reloc_give_up_m": "mapfusion.relocalise.SearchParams.give_up_m = 1500.0 m",
    "reloc_radius_m": "mapfusion.relocalise.SearchParams.radius_m = 300.0 m",
    "reloc_radius_per_m": "mapfusion.relocalise.SearchParams.radius_per_m = 1.0 m/m",
    "road_fix_uturn_probability": "mapfusion.relocalise.ROAD_FIX_UTURN_PROBABILITY = 0.02",
    "reloc_register_m": "mapfusion.relocalise.SearchParams.register_m = 1000.0 m",
    "reloc_gap_margin_m": "mapfusion.relocalise.SearchParams.gap_margin_m = 100.0 m",
    "reloc_gap_guess_floor": "mapfusion.relocalise.SearchParams.gap_guess_floor = 0.05",
    "road_fix_after_gps_s": "mapfusion.tracking.RoadFixParams.after_gps_s = 2.0 s",
    "road_fix_hold_m": "mapfusion.tracking.RoadFixParams.hold_m = 50.0 m",
    "road_fix_gate_sigma": "mapfusion.tracking.RoadFixParams.gate_sigma = 5.0",
    "road_fix_cluster_m": "mapfusion.tracking.RoadFixParams.cluster_m = 25.0 m",
    "road_fix_kld_epsilon": "mapfusion.tracking.RoadFixParams.kld_epsilon = 0.05",
    "reloc_particles": "mapfusion.relocalise.ParticleParams.particles = 60000",
    "reloc_particles_per_m": "mapfusion.relocalise.ParticleParams.particles_per_m = 10.0 1/m",
    "reloc_particles_min": "mapfusion.relocalise.ParticleParams.particles_min = 500",
    "reloc_kld_epsilon": "mapfusion.relocalise.ParticleParams.kld_epsilon = 0.0",
    "reloc_kld_bin_m": "mapfusion.relocalise.ParticleParams.kld_bin_m = 5.0 m",
    "reloc_step_m": "mapfusion.relocalise.ParticleParams.step_m = 5.0 m",
    "reloc_sigma_m": "mapfusion.relocalise.ParticleParams.sigma_m = 1.5 m",
    "reloc_sigma_per_m": "mapfusion.relocalise.ParticleParams.sigma_per_m = 0.15 m/m",
    "reloc_scale_sigma": "mapfusion.relocalise.ParticleParams.scale_sigma = 0.03",
    "reloc_scale_walk": "mapfusion.relocalise.ParticleParams.scale_walk = 0.005",
    "reloc_along_sigma_m": "mapfusion.relocalise.ParticleParams.along_sigma_m = 0.5 m",
    "reloc_offset_gain": "mapfusion.relocalise.ParticleParams.offset_gain = 0.2",
    "reloc_offset_sigma_deg": "mapfusion.relocalise.ParticleParams.offset_sigma_deg = 0.3 deg",
    "reloc_offset_max_deg": "mapfusion.relocalise.ParticleParams.offset_max_deg = 180.0 deg",
    "reloc_uturn_probability": "mapfusion.relocalise.ParticleParams.uturn_probability = 0.0",
    "reloc_uturn_at_vertex": "mapfusion.relocalise.ParticleParams.uturn_at_vertex = 0.1",
    "reloc_converge_radius_m": "mapfusion.relocalise.ParticleParams.converge_radius_m = 25.0 m",
    "reloc_converge_mass": "mapfusion.relocalise.ParticleParams.converge_mass = 0.8",
    "reloc_min_distance_m": "mapfusion.relocalise.ParticleParams.min_distance_m = 100.0 m",
    "road_fix_particles": "mapfusion.tracking.RoadFixParams.particles = 20000",
    "road_fix_radius_m": "mapfusion.tracking.RoadFixParams.radius_m = 50.0 m",
    "road_fix_radius_max_m": "mapfusion.tracking.RoadFixParams.radius_max_m = 2000.0 m",
    "road_fix_scale_factor": "mapfusion.tracking.RoadFixParams.scale_factor = 1.3",
    "road_fix_every_m": "mapfusion.tracking.RoadFixParams.every_m = 5.0 m",
    "road_fix_min_mass": "mapfusion.tracking.RoadFixParams.min_mass = 0.8",
    "road_fix_restart_m": "mapfusion.tracking.RoadFixParams.restart_m = 300.0 m",
    "road_fix_agree_m": "mapfusion.tracking.RoadFixParams.agree_m = 20.0 m",
    "road_fix_agree_widths": "mapfusion.tracking.RoadFixParams.agree_widths = 2.5",
    "road_fix_rival_mass": "mapfusion.tracking.RoadFixParams.rival_mass = 0.05",
    "road_fix_sigma_m": "mapfusion.tracking.RoadFixParams.sigma_m = 3.0 m",
    "road_fix_offset_max_deg": "mapfusion.tracking.RoadFixParams.offset_max_deg = 5.0 deg",
    "road_fix_scale_gain": "mapfusion.tracking.RoadFixParams.scale_gain = 0.02",
    "road_fix_drift": "mapfusion.tracking.RoadFixParams.drift = 0.1",
    "road_fix_heading_sigma_deg": "mapfusion.tracking.RoadFixParams.heading_sigma_deg = 0.0 deg",
    "road_fix_heading_floor": "mapfusion.tracking.RoadFixParams.heading_floor = 0.01",
    "reloc_confirm_m": "mapfusion.relocalise.SearchParams.confirm_m = 5.0 m",
    "reloc_after_gps_s": "mapfusion.relocalise.SearchParams.after_gps_s = 10.0 s",
    "reloc_gps_replay_m": "mapfusion.relocalise.SearchParams.gps_replay_m = 500.0 m",
    "reloc_gps_fit_min": "mapfusion.relocalise.SearchParams.gps_fit_min = 0.75",
    "reloc_gps_fit_m": "mapfusion.relocalise.SearchParams.gps_fit_m = 300.0 m",
    "reloc_gps_fit_margin_m": "mapfusion.relocalise.SearchParams.gps_fit_margin_m = 3.0 m",
    "reloc_register_ratio": "mapfusion.relocalise.SearchParams.register_ratio = 1.25",
    "reloc_register_after_s": "mapfusion.relocalise.SearchParams.register_after_s = 2.0 s",
    "reloc_register_place_m": "mapfusion.relocalise.SearchParams.register_place_m = 150.0 m",
    "reloc_register_rms_m": "mapfusion.relocalise.SearchParams.register_rms_m = 4.0 m",
    "reloc_register_separation_m": "mapfusion.relocalise.SearchParams.register_separation_m = 30.0 m",
    "reloc_mend_keep_ratio": "mapfusion.relocalise.SearchParams.mend_keep_ratio = 0.5",
    "reloc_doubt_m": "mapfusion.relocalise.SearchParams.doubt_m = 1000.0 m",
    "reloc_watch_m": "mapfusion.relocalise.SearchParams.watch_m = 500.0 m",
    "reloc_watch_apart_m": "mapfusion.relocalise.SearchParams.watch_apart_m = 50.0 m",
    "reloc_rival_mass": "mapfusion.relocalise.SearchParams.rival_mass = 0.05",
    "reloc_gap_speed_mps": "mapfusion.relocalise.SearchParams.gap_speed_mps = 15.0 m/s",
    "reloc_gap_reach_sigmas": "mapfusion.relocalise.SearchParams.gap_reach_sigmas = 1.0",
    "reloc_max_radius_m": "mapfusion.relocalise.SearchParams.max_radius_m = 2000.0 m",
    "planar_steps": "level (mapfusion.track.track_for: body and world were measured worse)",
}


@dataclass(frozen=True)
class FusionConfig:
    """Parameters of the Map-Fusion engine; the ``[mapfusion]`` table of a scenario file."""

    #: Keys a scenario file may still hold, with what became of them (the loader refuses them with this line).
    RETIRED_KEYS: ClassVar[dict[str, str]] = {
        "road_tracking": "was removed: the map prior's road is each frame's match (the road hypotheses remain in "
                         "mapfusion maps stress --sequence)",
        **{f"hmm_{k}": "was removed with road_tracking" for k in ("emission_scale_m", "transition_scale_m",
                                                                  "jump_penalty", "beam", "min_posterior", "step_m")},
        "hmm_lost_cost_m": "is renamed lost_cost_m",
        "hmm_lost_after_m": "is renamed lost_after_m",
        "reloc_hold_m": "was removed (measured worse: on 20 kidnapped runs, holding 50 / 100 m found 9 / 9 within "
                        "500 m against 12)",
        "prior_gate_sigma": "was removed (measured worse: on a 40-run rain set 8.48 m at 3 σ against 3.23 m "
                            "without)",
        "match_continuity": "was removed (measured worse: once on a wrong road it kept the estimate there)",
        "continuity_slack_m": "was removed with match_continuity",
        "scale_sigma_honest": "was removed (measured worse on the held-out 60-run set, 8.38 -> 9.55 m)",
        "reloc_reweigh_held": "was removed (measured: it re-anchored a good estimate 124 m onto a look-alike on the "
                              "kidnapped seeds 21-30)",
        **{k: "was removed (measured worse: kidnapped seeds 11-20 after-error 9.71 -> 15.71 m, three rain-tunnel "
              "runs worse)" for k in ("reloc_reverse_deg", "reloc_reverse_reach_m", "road_fix_reverse_deg")},
        "road_fix_steady_start": "was removed (measured worse: the 60-run set 7.21 -> 8.10 m); a start after a "
                                 "re-anchoring always waits for a steady heading",
        "road_fix_near_only": "was removed (measured worse on rain-tunnel with GPS at the start only: three runs "
                              "worse, none better)",
        "road_fix_while_searching": "was removed: the road fixes always wait while a map search runs",
        "reloc_lost_scale_factor": "was removed (measured worse: rain-tunnel with GPS at the start only 62.53 -> "
                                   "64.27 m; kitti-real with the search 44.39 m against 38.61 m without it)",
        "traffic_side": "was removed (measured worse: a real TrianFlow drive 23.8 -> 82.5 m, worse than without the "
                        "map, and rain 7.83 -> 9.93 m)",
        "reloc_under_gps": "was removed: the search runs beside GPS once the estimate is lost (false: a search begun "
                           "only at GPS's silence re-anchored later: 145.1 / 92.8 / 95.2 s against 97.2 / 83.3 / 94.6"
                           " s)",
        "reloc_register_on_roads": "was removed: GPS's last fixes are registered wherever the estimate is (false: "
                                   "kidnapped seeds 1-10 within 500 m 37 -> 36 of 40)",
        "reloc_gap_guess_along": "was removed: the gap's guess spans the whole carried step (false: a vehicle that "
                                 "stopped in the gap was searched for 574 m)",
        "reloc_gap_keeps_region": "was removed: a gap's search also covers a running search's region (false: rain-"
                                  "tunnel Helsinki vo s3 searched 133 m around an estimate 480 m off)",
        "reloc_rival_outside_answer": "was removed: the rival mass is counted outside the answer's disc (false: "
                                      "corrections of 15-75 m were never made)",
        "gps_reach_back": "was removed: a GPS re-localisation always mends the stretch since the last fix (false: "
                          "rain-tunnel drifted 50-135 m in GPS-denied zones)",
        "outage_turn": "was removed: the carried step always turns with the odometry at a junction (false: a 94 deg "
                       "turn in an 8 s gap ended 85 m off)",
        "reloc_mend_back": "was removed: a map re-anchoring always mends the searched path (false: its frames kept a "
                           "148 m bias)",
        "road_fix_trust_fit": "was removed: with map_relocalisation the road fixes are always kept near an estimate "
                              "on the roads (false: kidnapped seeds 1-10 / 11-20 ATE 37.31 / 50.30 -> 40.38 / 50.33 "
                              "m)",
        **{k: f"is no longer a setting: fixed as {v}" for k, v in _FIXED_KEYS.items()},
    }

    lane_width_m: float = param(
        3.0,
        "Width of one lane; road width = lanes × lane width.",
        unit="m",
        min=0.5,
        max=10.0,
        source="paper III.B ('approximated to be 3m per lane')",
    )
    yaw_sigma_deg: float = param(
        10.0,
        "Standard deviation of the map prior's yaw.",
        unit="deg",
        min=0.1,
        max=180.0,
        source="paper III.B ('empirically set as 10 degrees')",
    )
    angle_weight_m_per_deg: float = param(
        1.0,
        "Weight w of the angle in D = E + w·A.",
        unit="m/deg",
        min=0.0,
        max=100.0,
        source="paper III.B ('each degree difference corresponds to 1m')",
    )
    search_radius_m: float = param(
        20.0,
        "Radius around the predicted pose searched for map way-points.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        max=500.0,
        source="paper IV.B ('within a 20m radius')",
    )
    scale_min_distance_m: float = param(
        100.0,
        "md: distance the GPS must cover before a scale sample is taken.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        source="paper III.C (md); value by measurement",
    )
    scale_min_speed_kmh: float = param(
        10.0,
        "ms: minimum average speed for a scale sample.",
        unit="km/h",
        min=0.0,
        exclusive_min=True,
        source="paper III.C (ms); value by measurement",
    )
    scale_samples: int = param(
        50,
        "Scale samples whose median is the scale.",
        min=1,
        max=10000,
        source="paper III.C ('50 samples were sufficient')",
    )
    scale_formula: ScaleFormula = param(
        ScaleFormula.speed_ratio, "Scale estimator: speed_ratio or paper (the printed form).", source="DESIGN item 4"
    )
    odometry_sigma_before_init_m: float = param(
        10.0,
        "Translation σ of an odometry step before scale initialisation.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        source="paper IV.B ('highly uncertain')",
    )
    odometry_sigma_after_init_m: float = param(
        0.005,
        "Translation σ of an odometry step after scale initialisation.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    odometry_rot_sigma_deg: float = param(
        0.01,
        "Rotation σ of an odometry step after initialisation.",
        unit="deg",
        min=0.0,
        exclusive_min=True,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    odometry_sigma_per_m: float = param(
        0.015,
        "Translation σ of an odometry step per metre it moves, combined in quadrature with "
        "odometry_sigma_after_init_m: a real odometry's error grows with the distance driven, not "
        "with the frames (a stopped vehicle's VO does not drift).",
        unit="m/m",
        min=0.0,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    odometry_rot_sigma_deg_per_m: float = param(
        0.035,
        "Rotation σ of an odometry step per metre it moves, combined in quadrature with "
        "odometry_rot_sigma_deg.",
        unit="deg/m",
        min=0.0,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    odometry_sigma_learned: bool = param(
        True,
        "Learn the odometry's σ from the GPS window at initialisation: the four odometry σ above are multiplied by "
        "the drift a similarity fit to the window's fixes leaves beyond the fixes' own noise over the residual those "
        "σ would leave on the same path (odometry_trust.py): loosened only as far as the drift's lower bound shows, "
        "tightened only as far as its upper bound shows, within odometry_sigma_factor_min..max. A cold start, "
        "without fixes, takes odometry_sigma_cold_factor.",
        source="issue 17: real and simulated VO drift 2-17x what the configured σ allow over the window, KITTI's own "
               "poses 0.3-1x; learned (two-sided, max 3): kitti-real 50.8 -> 38.6 m, heavy-rain 5.08 -> 3.55 m, "
               "held-out 60 drives 6.07 -> 4.79 m, every family better (docs/method.md)",
    )
    odometry_sigma_factor_min: float = param(
        1.0,
        "Smallest factor the learned odometry σ may put on the configured σ (1: it only loosens them).",
        unit="1",
        min=0.0,
        exclusive_min=True,
        max=100.0,
        source="issue 17: tightened (0.05) KITTI's own poses drift 0.3-1x the configured σ, but 01 without the map "
               "0.112 -> 0.178 m (docs/method.md)",
    )
    odometry_sigma_cold_factor: float = param(
        2.0,
        "The factor on the configured odometry σ after a cold start (start_in_region), when odometry_sigma_learned "
        "is on: no GPS window measured this odometry's drift, so it is taken between a good odometry's 1 and the "
        "drifting VOs' 3.",
        unit="1",
        min=0.0,
        exclusive_min=True,
        max=100.0,
        source="issue 17: cold starts on the five KITTI drives, RMSE summed over them, factor 1 / 2 / 3: simulated "
               "rain VO 36.7 / 30.8 / 30.0 m, clear VO 30.6 / 27.8 / 26.7, rain VIO 34.1 / 28.6 / 27.3, real stereo "
               "VO 50.6 / 48.3 / 47.5, clear VIO 18.9 / 19.2 / 22.0, KITTI's own poses 15.3 / 15.9 / 19.6 m "
               "(docs/method.md)",
    )
    odometry_sigma_factor_max: float = param(
        3.0,
        "Largest factor the learned odometry σ may put on the configured σ.",
        unit="1",
        min=0.0,
        exclusive_min=True,
        max=100.0,
        source="issue 17: 3 / 5 / 10 measured over the families, kitti-real and kidnapped; 10 worse on kitti-realism "
               "(11.1 -> 11.5 m) and kitti-real (docs/method.md)",
    )
    gps_sigma_m: float = param(
        2.0,
        "σ of a GPS position factor when the fix carries none.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        source="paper IV.B ('set to a predefined value')",
    )
    gps_gate_sigma: float = param(
        5.0,
        "Mahalanobis gate: fixes farther than this many σ are rejected.",
        min=0.0,
        exclusive_min=True,
        source="robustness (issue 6)",
    )
    backend: Backend = param(
        Backend.fixed_lag,
        "fixed_lag (bounded cost, default) or isam2 (whole history, as the paper).",
        source="DESIGN item 6",
    )
    lag_s: float = param(
        10.0, "Window of the fixed-lag smoother.", unit="s", min=0.0, exclusive_min=True, source="value by measurement"
    )
    delocalization_m: float = param(
        20.0,
        "ATE above which a run counts as de-localised.",
        unit="m",
        min=0.0,
        exclusive_min=True,
        source="paper IV.B ('widest road observed')",
    )
    use_map: bool = param(
        True, "Add map priors; false gives the odometry baseline (same GPS use).", source="paper IV.B"
    )
    state: StateModel = param(
        StateModel.planar,
        "planar (level ground vehicle) or pose3 (the paper's free Pose3).",
        source="DESIGN item 7; chosen by measurement",
    )
    odometry_nonholonomic: bool = param(
        True,
        "Each odometry step moves the vehicle along its heading (the mean of the step's start and end yaw), "
        "forwards or backwards, by the step's own length: a wheeled vehicle does not slide sideways, so a "
        "sideways component of the measured step (a VO's lateral drift, as raindrops on the lens make) is "
        "an error of the odometry, not motion; false: the step as measured (the paper). Steps across gaps over a "
        "second are left as measured.",
        source="issue 17: the cold start on KITTI 01 in rain slid 8 m across its trunk road in 3 s, "
        "heading right, and was matched to a parallel service road; with odometry_slip_deg 3 and the gated "
        "heading priors every family measured (docs/method.md, \"A wheeled vehicle does not slide\")",
    )
    odometry_slip_deg: float = param(
        3.0,
        "With odometry_nonholonomic: a step goes along its heading only while the odometry slides, its last "
        "second's steps (less the lever arm's swing) moving sideways at more than this angle to their heading: "
        "a good odometry's own direction of motion is better than its integrated heading, a VO's slide in rain "
        "is not; 0: every step along its heading.",
        unit="deg", min=0.0, max=90.0,
        source="issue 17: 3 keeps KITTI's good VIO as it was (the real drives slip in turns; "
        "at 0 KITTI 02 clear VIO s2 0.59 -> 2.46 m ATE; docs/method.md)",
    )
    prior_mode: PriorMode = param(
        PriorMode.along_free,
        "paper (σ along the road from |v_lon|) or along_free.",
        source="DESIGN items 3 and 7; chosen by measurement",
    )
    prior_lambda_floor_m2: float = param(
        0.25,
        "Floor of the prior's eigenvalues λ1, λ2 (variances), so Σ is never singular.",
        unit="m²",
        min=0.0,
        exclusive_min=True,
        source="DESIGN item 3",
    )
    prior_map_sigma_m: float = param(
        1.0,
        "σ of the map's own geometry (OSM centre lines are off by metres, a vehicle drives in a lane, "
        "not on the centre line), added in quadrature to both of the prior's eigenvalues; 0: the paper's "
        "prior, whose σ is the velocity's alone.",
        unit="m",
        min=0.0,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    prior_target: PriorTarget = param(
        PriorTarget.edge,
        "centre: the prior puts the vehicle on the road's centre line (the paper); edge: on the nearest "
        "edge of the band |lateral| ≤ road width, with the paper's σ; band: the map says "
        "only that the vehicle is within the road width of the centre line, and the prior is that band's "
        "information given the estimate's own lateral σ (a certain estimate is moved to the band's edge, "
        "an uncertain one towards the centre).",
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    prior_spacing_m: float = param(
        10.0,
        "At most one map prior per this much driving: priors from the same stretch of road share "
        "its geometry's error and are not independent measurements; 0: a prior on every frame off "
        "its road (the paper).",
        unit="m",
        min=0.0,
        source="issue 16: by measurement on real VO, KITTI ground truth as odometry and a 60-run set (docs/method.md)",
    )
    robust_kernel: RobustKernel = param(
        RobustKernel.huber, "none | huber | cauchy on the map prior.", source="DESIGN item 7"
    )
    robust_k: float = param(
        1.345,
        "Threshold of the robust kernel, in σ (whitened units).",
        min=0.0,
        exclusive_min=True,
        source="Huber's 95%-efficiency constant",
    )
    prior_max_angle_deg: float = param(
        30.0,
        "No map prior from a match whose angle A exceeds this: a road heading "
        "that far from the vehicle's is the crossing road at a junction.",
        unit="deg",
        min=0.0,
        max=180.0,
        source="DESIGN item 7 (wrong-road priors at turns); by measurement",
    )
    heading_prior_sigma_deg: float = param(
        3.0,
        "σ of a heading prior on an estimate that lies on its road (within the width that calls for a map prior), "
        "heading within heading_prior_max_deg of it, on a straight stretch: the road's heading in yaw alone, at most "
        "one per heading_prior_spacing_m of driving. The paper's map prior corrects only an estimate already off "
        "its road, so a heading error grows unchecked inside the band until the estimate leaves it, by then often "
        "nearer a parallel road; 0: none (the paper).",
        unit="deg",
        min=0.0,
        max=90.0,
        source="issue 17: 3 is the best measured (2 / 3 / 5 on the 60-run set, GPS at the start only, "
        "with odometry_nonholonomic: ATE 4.60 / 3.85 / 4.05 m against 5.10 m without either); ungated it bends a good "
        "VIO to OSM's drawing (KITTI 02 clear VIO 0.59 -> 1.4 m), hence heading_prior_gate (docs/method.md)",
    )
    heading_prior_spacing_m: float = param(
        10.0, "At most one heading prior per this much driving.", unit="m", min=0.0,
        source="as prior_spacing_m",
    )
    heading_prior_gate: float = param(
        1.0,
        "A heading prior only while the estimate's marginal yaw σ is at least this many heading_prior_sigma_deg: "
        "a good odometry's heading, known better than the road's, is not pulled to OSM's drawing (0: always).",
        unit="1", min=0.0, max=100.0,
        source="issue 17: 1 keeps KITTI's good VIO as it was (every clear VIO within 0.08 m); "
        "alone it lost Helsinki heavy rain s5 (online RMSE 5.7 -> 155 m: the marginal σ of a VO in heavy rain is "
        "optimistic), hence heading_prior_open_factor; 0.3: kitti-full 3.05 m but 4 runs worse than the odometry",
    )
    heading_prior_open_factor: float = param(
        1.5,
        "heading_prior_gate stays open while the learned odometry σ factor (odometry_sigma_learned) exceeds this: "
        "the GPS window found the odometry worse than configured, so its own marginal yaw σ is optimistic "
        "(0: the gate alone decides).",
        unit="1", min=0.0, max=100.0,
        source="issue 17: the learned factor reads 1.00 on KITTI's clear VIO and 3.00 on Helsinki "
        "heavy rain s5, whose heading priors the gate at 1 shut out (docs/method.md)",
    )
    prior_ambiguity_m: float = param(
        3.0,
        "No map prior when another way's best D is within this of the match's: "
        "at junctions and beside parallel roads the match is a coin toss.",
        unit="m",
        min=0.0,
        source="DESIGN item 7; by measurement",
    )
    prior_ambiguity_line_m: float = param(
        1.0,
        "Ways that continue the match's road are not its rivals for prior_ambiguity_m: another way's way-points "
        "within this of the match's road line (its way-point and heading), heading within 10 degrees of it, are "
        "the same road (a way split in two, or drawn twice); 0: every other way is a rival (the gate as it was).",
        unit="m",
        min=0.0,
        source="issue 17: on Helsinki, whose ways are split every few tens of metres, 705 of 950 frames "
        "that wanted a prior were gated as ambiguous on a drive with no GPS, the rival the next way of the same road; "
        "1 m: kidnapped after-error 8.46 -> 7.93 m, 60-run set ATE 7.22 -> 7.01 m (docs/method.md)",
    )
    prior_on_joins: bool = param(
        False,
        "Allow map priors from way-points on the rounded joins inside junctions.",
        source="DESIGN item 7; by measurement",
    )
    odometry_priors: bool = param(
        True,
        "Add the odometry estimate as a prior when the marginal positional σ exceeds the road width.",
        source="paper IV.B",
    )
    relocalise_after_fixes: int = param(
        3,
        "Consecutive gated fixes that agree with each other and with the "
        "odometry's distances before the estimate is re-initialised from GPS.",
        min=2,
        max=100,
        source="robustness (issue 6); by measurement",
    )
    relocalise_track_fixes: int = param(
        10,
        "Consecutive gated fixes that agree with each other as a vehicle's track (each within reach of the one "
        "before at relocalise_track_speed_mps, plus the gate) re-initialise the estimate from GPS even where the "
        "odometry's distances disagree with them (a VO that stalled, jumped or lost its scale); 0: never.",
        min=0,
        max=1000,
        source="issue 16 (real TrianFlow on KITTI 01: 80 RTK fixes in a row rejected after the VO stalled)",
    )
    relocalise_rescale_min_sigmas: float = param(
        30.0,
        "A track run (relocalise_track_fixes) whose GPS chord is at least this many fix σ long also re-scales the "
        "odometry: its scale times the run's GPS chord over the estimate's chord between the same frames (the run "
        "fired because the odometry's distances disagree with the fixes': a mono VO whose scale collapsed keeps it "
        "collapsed after the re-anchoring); at 30 σ the ratio is known to 5%.",
        unit="fix σ",
        min=0.0,
        source="issue 16 (real TrianFlow on KITTI 01: the VO's scale fell about eightfold at 21.8 s)",
    )
    relocalise_rescale_max: float = param(
        20.0,
        "Largest factor (up or down) a track run re-scales the odometry by; beyond it the odometry stopped or "
        "leapt rather than changed its scale, and is left as it is (1: a track run never re-scales).",
        min=1.0,
        source="issue 16; a VO reporting under 1/20 of the motion has no scale to measure",
    )
    loose_before_init: bool = param(
        False,
        "Frames before initialisation enter with odometry_sigma_before_init_m "
        "(the paper, for frames whose scale is unknown); false: with the post-initialisation "
        "σ inflated by the scale's uncertainty, since the batch is solved once the scale is known.",
        source="paper IV.B; by measurement",
    )
    scale_fit_max_disagreement_sigma: float = param(
        3.0,
        "Let a least-squares scale fit replace the windows' median "
        "only when the two agree within this many combined σ: a drift "
        "inside the window can bend the odometry's shape so that the "
        "similarity fit absorbs it as scale; 0: always use the fit.",
        min=0.0,
        source="issue 6 (rain: fits 3-5% off where the median was within 0.1%); by measurement",
    )
    refine_scale: bool = param(
        True,
        "Keep refining the scale while GPS fixes arrive after initialisation.",
        source="issue 6 (a 30 s window overestimated the scale by 6%)",
    )
    factorization: Factorization = param(Factorization.qr, "QR or CHOLESKY for ISAM2.", source="DESIGN item 7")
    lost_cost_m: float = param(20.0, "A frame is unexplained by the map when no road's D = E + w·A is within this.",
                               unit="m", min=0.0, exclusive_min=True, source="issue 16 (divergence detection)")
    lost_after_m: float = param(100.0, "The estimate is lost after this much driving unexplained by the map (or with "
                                "no road in range); watched with map_relocalisation.", unit="m", min=0.0,
                                exclusive_min=True, source="issue 16 (divergence detection)")
    map_relocalisation: bool = param(False, "When the estimate is lost (no road explains it for lost_after_m), "
                                     "re-localise it on the road network from the odometry's shape alone and "
                                     "re-anchor the smoother there.", source="issue 17 (Brubaker et al. 2013, Lost!)")
    reloc_scale_min: float = param(1.0, "Smallest odometry scale (map metres per odometry unit) a cold start searches "
                                   "over; with reloc_scale_max above it the scale is unknown and found with the "
                                   "position (fuse --scale-unknown). 1 and 1: a metric odometry, taken as given.",
                                   unit="m/unit", min=1e-6, max=1e6, source="issue 17 item 2")
    reloc_scale_max: float = param(1.0, "Largest odometry scale a cold start searches over (see reloc_scale_min).",
                                   unit="m/unit", min=1e-6, max=1e6, source="issue 17 item 2")
    reloc_gap_s: float = param(2.0, "An odometry gap longer than this (the VO lost track and re-initialised) opens "
                               "the GPS gate (two agreeing fixes re-anchor, back to the gap), takes the step across "
                               "it along the road (outage_step) and, with map_relocalisation, starts a search "
                               "around the estimate before it.", unit="s", min=0.0, exclusive_min=True,
                               max=86400.0, source="issue 17: a VO re-initialises with a pose jump; issue 16: 3 s "
                               "took the simulated VO's 2-3 s re-initialisations (it re-matches gaps up to 2 s) "
                               "for bridged, and a 2.3 s one's guessed turn lost Kotka heavy rain s2 (208 m; 4.8 m "
                               "at 2 s): 60 runs seeds 1-10 10.61 -> 7.35 m, held-out 11-20 6.30 -> 6.32 m")
    road_fixes: bool = param(True, "While GPS is silent, road-network particles (the re-localisation's, the "
                             "odometry's scale a state of each) follow the vehicle from the estimate, and their "
                             "confident position enters the graph as a fix: the map's own answer to where the "
                             "vehicle is, from the odometry's shape over many junctions, independent of the "
                             "estimate's single road association.", source="issue 16 items 3-4, issue 17 (Lost!)")
    # --- initialisation details (issue 15: every number the engine uses is a documented field)
    init_stall_s: float = param(
        5.0,
        "Initialise with fewer than scale_samples samples when no fix came for this "
        "long (GPS ended before the window filled).",
        unit="s",
        min=0.0,
        exclusive_min=True,
        source="robustness (issue 6)",
    )
    init_fit_min_extent_m: float = param(
        20.0,
        "When GPS stalls (init_stall_s) before the scale windows took init_stall_min_samples samples (fixes that "
        "never spanned a chord of scale_min_distance_m: a drive circling a block), initialise by a least-squares "
        "similarity fit to the fixes if they spread at least this far (RMS about their mean; at least "
        "scale_fit_min_fixes fixes); 0: wait for more fixes, as before.",
        unit="m", min=0.0, max=10000.0,
        source="issue 17 (never lost for good): a 3 km Helsinki drive whose 40 s of fixes circled a block (RMS spread "
               "35 m, largest chord over 36 fixes 105 m) never initialised; 20 m: a 2 m σ fix spread over 20 m "
               "fixes the heading to ~1° with 10 fixes",
    )
    outage_step: OutageStep = param(
        OutageStep.road,
        "The motion across an odometry gap longer than reloc_gap_s: the odometry's own step; the last "
        "plausible velocity straight on; or (road) as far along the road graph from the road the estimate "
        "was matched to, taking at a junction the exit nearest the guess (outage_turn; without the map, or "
        "off any road: straight on). A VO that lost track guesses where it resumed: the simulated VO "
        "carries its last turn over the whole gap and resumed hundreds of metres off in tunnels.",
        source="issue 17 (rain-tunnel: 363–693 m off on resuming after 25 s in a straight tunnel)",
    )
    outage_speed_after_s: float = param(
        1.0,
        "With outage_step = road: this long after the odometry resumes from a gap, the gap's step is carried "
        "again at the mean of the speeds before the gap and since it resumed (not the speed before alone), and the "
        "smoother restarts before the gap with it, when the two lengths differ by more than 5% and 10 m (0: off; "
        "the speed before the gap only).",
        unit="s", min=0.0, max=60.0,
        source="issue 17 (rain-tunnel Andorra vo s2: 106 s in a tunnel carried at the 22.5 m/s before it, the "
               "vehicle at 27 m/s inside: 469 m short); 1 s: rain-tunnel with GPS at the start only 75.8 -> 58.2 m, "
               "kidnapped 37.2 -> 33.0 m, no run of 72 worse (docs/method.md)",
    )
    outage_end_weight_m_per_deg: float = param(
        1.0,
        "With outage_step = road: of the drives along the graph, the end taken is the one nearest the guess by "
        "D = E + w·A, this w (E: metres to the guess's position, A: degrees from the guess's heading, the last "
        "heading turned by the odometry's own turn over the gap); 0: the nearest by position alone, which took a "
        "drive that had just turned into a side street at a junction near the guess (position right, heading 90° "
        "off, the estimate then driven across blocks).",
        unit="m/deg", min=0.0, max=100.0,
        source="paper III.B's w; issue 17 (kidnapped VO jumps: 8 of 60 carried steps 31–90° off the road's heading)",
    )
    outage_step_fraction: float = param(
        0.3, "Translation σ of an outage step as a fraction of its length.", min=0.0, source="by measurement"
    )
    gps_gate_floor_m: float = param(
        1.0,
        "Added (in quadrature) to the gate's spread, so a confident estimate does not reject good fixes.",
        unit="m",
        min=0.0,
        source="robustness (issue 6)",
    )
    odometry_prior_rot_sigma_deg: float = param(
        10.0,
        "Rotation σ of the odometry prior (paper IV.B); its x/y σ is the road width.",
        unit="deg",
        min=0.0,
        exclusive_min=True,
        max=180.0,
        source="paper IV.B; was yaw_sigma_deg's value, now its own field (issue 15)",
    )
    # ---- wheel speed and gyro (issue 18): a second motion source, used only when both are fed
    wheel_sigma_per_m: float = param(
        0.005,
        "Along-track σ of the wheel's distance per metre driven, once its scale is calibrated: weighs the "
        "wheel against the odometry in each fused step.",
        unit="m/m",
        min=0.0,
        exclusive_min=True,
        max=1.0,
        source="issue 18: tyre radius known to 0.5% after calibration; quantisation and noise average out per metre",
    )
    wheel_lateral_sigma_per_m: float = param(
        0.01,
        "Lateral σ of the wheel + gyro step per metre (side slip: a car does not move sideways).",
        unit="m/m",
        min=0.0,
        exclusive_min=True,
        max=1.0,
        source="issue 18: slip angles under 0.5° in normal driving",
    )
    gyro_sigma_radps: float = param(
        0.002,
        "σ of the yaw rate after bias removal (noise and the bias estimate's error): weighs the gyro's yaw "
        "against the odometry's.",
        unit="rad/s",
        min=0.0,
        exclusive_min=True,
        max=1.0,
        source="issue 18: a consumer MEMS gyro (0.011 °/s/√Hz white noise, bias tracked against the VO)",
    )
    gyro_bias_time_constant_s: float = param(
        60.0,
        "The gyro bias is the yaw rate the gyro reads beyond the odometry's (or beyond zero at standstill), "
        "averaged with exponential forgetting over this time constant.",
        unit="s",
        min=1.0,
        max=86400.0,
        source="issue 18: the IMU model's bias random walk (2e-5 rad/s²/√Hz) moves the bias by ~1e-4 rad/s a minute",
    )
    wheel_gate_m: float = param(
        0.5,
        "An odometry step farther than wheel_gate_m + wheel_gate_fraction × the wheel's distance from the wheel + "
        "gyro step (or turning more than wheel_gate_deg differently) is a VO failure (a jump, a re-initialisation): "
        "counted (odometry_vetoed) and replaced by the wheel + gyro step.",
        unit="m",
        min=0.0,
        max=1000.0,
        source="issue 18: VO re-initialisation jumps of metres; a clear 0.1 s step agrees within centimetres",
    )
    wheel_gate_fraction: float = param(
        0.3, "See wheel_gate_m: the part of the gate proportional to the distance driven.", unit="1", min=0.0,
        max=10.0, source="issue 18: rain drift 0.1 m/m and an uncalibrated VO scale of a few % stay inside",
    )
    wheel_gate_deg: float = param(
        3.0, "See wheel_gate_m: the yaw part of the gate.", unit="deg", min=0.0, exclusive_min=True, max=180.0,
        source="issue 18: a 0.1 s step's yaw agrees within hundredths of a degree; a VO re-initialisation turns by "
        "degrees",
    )
    wheel_scale_sigma: float = param(
        0.02,
        "σ of the wheel scale (true metres per wheel metre) before calibration; GPS fits replace it once they are "
        "more certain.",
        unit="1",
        min=0.0,
        exclusive_min=True,
        max=0.5,
        source="issue 18: tyre radius errors of 0.5–2% (wear, pressure, load)",
    )

    def __post_init__(self) -> None:
        # a mode given as its name ("band") is the mode: the engine compares modes by identity, and a string
        # would silently take another branch
        for name, tp in _enum_fields(type(self)):
            value = getattr(self, name)
            if not isinstance(value, tp):
                object.__setattr__(self, name, _convert(value, tp, name, "FusionConfig"))
        if self.reloc_scale_min > self.reloc_scale_max:
            raise ConfigError(f"reloc_scale_min ({self.reloc_scale_min:g}) exceeds reloc_scale_max "
                              f"({self.reloc_scale_max:g})")
        if self.odometry_sigma_factor_min > self.odometry_sigma_factor_max:
            raise ConfigError(f"odometry_sigma_factor_min ({self.odometry_sigma_factor_min:g}) exceeds "
                              f"odometry_sigma_factor_max ({self.odometry_sigma_factor_max:g})")

    @classmethod
    def faithful(cls, **changes) -> FusionConfig:
        """A direct reading of the paper's section III: free Pose3, the Eq. 6 prior with |v_lon| along
        the road, no robust kernel, no matching continuity or angle gate, ISAM2 over the whole
        history, the scale fixed at initialisation. Kept for comparison (DESIGN item 7)."""
        base = dict(
            state=StateModel.pose3,
            prior_mode=PriorMode.paper,
            robust_kernel=RobustKernel.none,
            prior_max_angle_deg=180.0,
            prior_ambiguity_m=0.0,
            prior_on_joins=True,
            backend=Backend.isam2,
            refine_scale=False,
            loose_before_init=True,
            prior_target=PriorTarget.centre,
            prior_spacing_m=0.0,
            prior_map_sigma_m=0.0,
            odometry_sigma_after_init_m=0.05,
            odometry_rot_sigma_deg=0.5,
            odometry_sigma_per_m=0.0,
            odometry_rot_sigma_deg_per_m=0.0,
            odometry_sigma_learned=False,
            odometry_nonholonomic=False,
            odometry_slip_deg=0.0,
            heading_prior_sigma_deg=0.0,
            heading_prior_gate=0.0,
            heading_prior_open_factor=0.0,
        )
        base.update(changes)
        return cls(**base)  # type: ignore[arg-type]
