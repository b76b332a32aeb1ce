"""Methods scored beside the odometry and Map-Fusion: estimators as plug-ins (DESIGN "Estimators").

A scenario's ``[[estimators]]`` names each one (:class:`sim.scenario.EstimatorSpec`). Two forms:

- **A Python class** (``use = "module:Class"``, or the name of an entry point in the group
  ``mapfusion.estimators``), made once per run as ``Class(road, **params)`` (``road``: the run's
  :class:`~mapfusion.roadmap.RoadMap`, whose ``projection`` is the map's ENU frame) and fed the run's inputs in time
  order, through the engine's own streaming calls (:class:`StreamingEstimator`): at equal times wheel and gyro
  first, then GPS, then the odometry frame. After every odometry frame its ``estimate()`` is the causal estimate
  scored; None before it has one.
- **An external command** (``command = "..."``): run once per run with the run's inputs as files (full precision:
  every value as Python writes a float) and expected to write a TUM estimate in the map's ENU frame
  (:data:`sim.scenario.COMMAND_FILES`). For methods in other languages, or in ROS behind a script.

Both get what Map-Fusion gets: the odometry (relative poses, body frame: x forward, y left, z up; unscaled as the
sensor gave them), the GPS fixes the run's GPS mode lets through, and wheel speed and gyro only where the odometry
kind has a wheel (``vo+wheel``, ``vio+wheel``). A failing estimator (an exception, a crash, a timeout, an
unreadable estimate) fails its own column with one line; the run and the other estimators go on.
"""

from __future__ import annotations

import importlib
import logging
import math
import subprocess
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from mapfusion.errors import InputError
from mapfusion.formats import GpsFixes
from mapfusion.replay import MotionSamples
from sim.scenario import COMMAND_FILES, EstimatorSpec, command_arguments

log = logging.getLogger(__name__)

#: The entry point group a package registers its estimators under (name → "module:Class").
ENTRY_POINT_GROUP = "mapfusion.estimators"


@runtime_checkable
class StreamingEstimator(Protocol):
    """What a Python estimator implements. ``add_wheel_speed`` and ``add_imu`` are optional: a class without them
    is not fed wheel or IMU samples. An offline method adds ``final_estimates() -> (t_s, poses)``: called once after
    the last input, its answer is scored instead of the causal ``estimate()``s."""

    def add_odometry(self, t_s: float, relative_pose: np.ndarray) -> None:
        """The motion since the previous frame (4 × 4, body frame), at time ``t_s``."""

    def add_gps(self, t_s: float, lat: float, lon: float, alt: float | None = None,
                sigma_m: float | None = None) -> None:
        """A fix: WGS84 degrees, altitude (m, None when unknown) and the receiver's σ (m, None when unknown)."""

    def estimate(self) -> Any:
        """The current pose in the map's ENU frame (4 × 4, or anything with ``.matrix()``), or None."""


class EstimatorError(Exception):
    """An estimator failed on a run: the message is the one line its column shows."""


@dataclass(frozen=True)
class Track:
    """An estimate to score: times (s), positions (N, 3) and yaw (rad) in the map's ENU frame."""

    t_s: np.ndarray
    xyz_m: np.ndarray
    yaw_rad: np.ndarray


def load_class(use: str) -> type:
    """The class ``use`` names (``module:Class``, or an entry point of :data:`ENTRY_POINT_GROUP`); an
    :class:`~mapfusion.errors.InputError` (one line) when it names nothing of the kind."""
    target = use
    if ":" not in use:
        found = [ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name == use]
        if not found:
            known = sorted(ep.name for ep in metadata.entry_points(group=ENTRY_POINT_GROUP))
            raise InputError(f"estimator {use!r}: give module:Class, or the name of a {ENTRY_POINT_GROUP} entry point "
                             f"({', '.join(known) if known else 'none installed'})")
        target = found[0].value
    module, _, name = target.partition(":")
    try:
        cls: Any = importlib.import_module(module)
        for part in name.split("."):
            cls = getattr(cls, part)
    except ImportError as exc:
        raise InputError(f"estimator {use!r}: cannot import {module} ({exc})") from None
    except AttributeError:
        raise InputError(f"estimator {use!r}: {module} has no {name}") from None
    if not isinstance(cls, type):
        raise InputError(f"estimator {use!r}: {target} is not a class")
    missing = [m for m in ("add_odometry", "add_gps", "estimate") if not callable(getattr(cls, m, None))]
    if missing:
        raise InputError(f"estimator {use!r}: {target} has no {', '.join(missing)} (see StreamingEstimator)")
    return cls


def _pose_matrix(p: Any) -> np.ndarray:
    m = np.asarray(p.matrix() if hasattr(p, "matrix") else p, dtype=float)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise EstimatorError(f"estimate() gave {m.shape if m.shape != (4, 4) else 'a non-finite'} pose, not a finite "
                             "4 × 4 matrix")
    return m


def _track(t: list[float], poses: list[np.ndarray]) -> Track:
    if not poses:
        raise EstimatorError("no estimate at all")
    m = np.asarray(poses)
    return Track(np.asarray(t, dtype=float), m[:, :3, 3], np.arctan2(m[:, 1, 0], m[:, 0, 0]))


def run_python(spec: EstimatorSpec, road, t_odo: np.ndarray, poses: np.ndarray, fixes: GpsFixes | None,
               motion: MotionSamples | None, imu=None) -> Track:
    """``spec``'s class fed one run's inputs (``poses``: absolute, the odometry's own frame); its causal estimates.
    ``imu``: (t_s, accel (N, 3), gyro (N, 3)) fed with the wheel where ``motion`` is given."""
    cls = load_class(spec.use)
    try:
        est = cls(road, **dict(spec.params))
    except Exception as exc:
        raise EstimatorError(f"{spec.use}({', '.join(k for k, _ in spec.params)}): {type(exc).__name__}: {exc}") from None
    events: list[tuple[float, int, int]] = []  # (t, order at equal times, index): wheel, imu, gps, frame
    if motion is not None and callable(getattr(est, "add_wheel_speed", None)):
        events += [(float(t), 0, i) for i, t in enumerate(motion.wheel_t_s)]
    if motion is not None and imu is not None and callable(getattr(est, "add_imu", None)):
        events += [(float(t), 1, i) for i, t in enumerate(imu[0])]
    if fixes is not None:
        events += [(float(t), 2, i) for i, t in enumerate(fixes.t_s)]
    events += [(float(t), 3, i) for i, t in enumerate(t_odo)]
    events.sort()
    out_t: list[float] = []
    out_p: list[np.ndarray] = []
    try:
        for t, kind, i in events:
            if kind == 0:
                est.add_wheel_speed(t, float(motion.wheel_speed_mps[i]))  # type: ignore[union-attr]
            elif kind == 1:
                est.add_imu(t, np.asarray(imu[1][i]), np.asarray(imu[2][i]))  # type: ignore[index]
            elif kind == 2:
                assert fixes is not None
                alt, sigma = float(fixes.alt_m[i]), float(fixes.sigma_m[i])
                est.add_gps(t, float(fixes.lat_deg[i]), float(fixes.lon_deg[i]), alt if math.isfinite(alt) else None,
                            sigma if math.isfinite(sigma) else None)
            else:
                if i == 0:
                    continue  # (the first frame has no motion before it)
                est.add_odometry(t, np.linalg.solve(poses[i - 1], poses[i]))
                p = est.estimate()
                if p is not None:
                    out_t.append(t)
                    out_p.append(_pose_matrix(p))
    except EstimatorError:
        raise
    except Exception as exc:
        raise EstimatorError(f"{type(exc).__name__} at t = {t:.2f} s: {exc}") from None
    if callable(getattr(est, "final_estimates", None)):  # an offline method: its answer after the whole drive
        try:
            t_all, final = est.final_estimates()
            return _track([float(v) for v in t_all], [_pose_matrix(p) for p in final])
        except EstimatorError:
            raise
        except Exception as exc:
            raise EstimatorError(f"final_estimates(): {type(exc).__name__}: {exc}") from None
    return _track(out_t, out_p)


def _write_inputs(d: Path, t_odo, poses, fixes: GpsFixes | None, motion: MotionSamples | None, imu) -> dict[str, str]:
    """The inputs as files, every value as Python writes a float (so a command reads what a class is fed)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    with open(d / "odometry.tum", "w") as f:
        f.write("# odometry: absolute poses in its own frame (body: x forward, y left, z up)\n# t tx ty tz qx qy qz qw\n")
        for t, p, qq in zip(t_odo, poses, q):
            f.write(" ".join(repr(float(v)) for v in (t, *p[:3, 3], *qq)) + "\n")
    with open(d / "gps.csv", "w") as f:
        f.write("t,lat,lon,alt,sigma_m\n")
        if fixes is not None:
            for i in range(len(fixes.t_s)):
                alt, s = float(fixes.alt_m[i]), float(fixes.sigma_m[i])
                f.write(f"{float(fixes.t_s[i])!r},{float(fixes.lat_deg[i])!r},{float(fixes.lon_deg[i])!r},"
                        f"{repr(alt) if math.isfinite(alt) else ''},{repr(s) if math.isfinite(s) else ''}\n")
    with open(d / "wheel.csv", "w") as f:
        f.write("t,speed_mps\n")
        if motion is not None:
            for t, v in zip(motion.wheel_t_s, motion.wheel_speed_mps):
                f.write(f"{float(t)!r},{float(v)!r}\n")
    with open(d / "imu.csv", "w") as f:
        f.write("t,ax,ay,az,gx,gy,gz\n")
        if motion is not None and imu is not None:
            for t, a, g in zip(*imu):
                f.write(",".join(repr(float(v)) for v in (t, *a, *g)) + "\n")
    return {"odometry": str(d / "odometry.tum"), "gps": str(d / "gps.csv"), "wheel": str(d / "wheel.csv"),
            "imu": str(d / "imu.csv"), "out": str(d / "estimate.tum")}


def run_command(spec: EstimatorSpec, map_path: str, t_odo, poses, fixes: GpsFixes | None,
                motion: MotionSamples | None, imu=None) -> Track:
    """``spec``'s command on one run's inputs (written to a temporary folder); the TUM estimate it wrote."""
    from mapfusion.formats import FormatError, read_tum

    with tempfile.TemporaryDirectory(prefix="mapfusion-estimator-") as tmp:
        files = _write_inputs(Path(tmp), t_odo, poses, fixes, motion, imu)
        files["map"] = str(map_path)
        assert set(files) == set(COMMAND_FILES)
        args = command_arguments(spec.command, files)
        try:
            p = subprocess.run(args, capture_output=True, text=True, timeout=spec.timeout_s, cwd=tmp)
        except FileNotFoundError:
            raise EstimatorError(f"{args[0]}: no such program") from None
        except subprocess.TimeoutExpired:
            raise EstimatorError(f"still running after {spec.timeout_s:g} s (timeout_s)") from None
        if p.returncode != 0:
            last = (p.stderr.strip().splitlines() or ["no message"])[-1]
            raise EstimatorError(f"{args[0]} exited {p.returncode}: {last}")
        try:
            t, xyz, q = read_tum(files["out"])
        except FileNotFoundError:
            raise EstimatorError("wrote no estimate to {out}") from None
        except FormatError as exc:
            raise EstimatorError(f"its estimate: {exc}") from None
    if len(t) == 0:
        raise EstimatorError("no estimate at all")
    x, y, z, w = q.T
    return Track(t, xyz, np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def run_estimator(spec: EstimatorSpec, road, map_path: str, t_odo, poses, fixes, motion, imu=None) -> Track:
    """Either form; :class:`EstimatorError` (one line) when it fails."""
    if spec.use:
        return run_python(spec, road, t_odo, poses, fixes, motion, imu)
    return run_command(spec, map_path, t_odo, poses, fixes, motion, imu)
