"""ROS bags in and out (``rosbags``: pure Python, no ROS installation): ROS 1 ``.bag`` and ROS 2
(sqlite3 and mcap) alike.

In: ``nav_msgs/Odometry`` (absolute poses; a child frame in the camera convention — an optical
frame — is turned into the body convention as ``--odometry-frame camera`` does),
``sensor_msgs/NavSatFix`` (status −1, no fix, skipped and counted; the position covariance gives
σ, an unknown covariance type the configured σ) and ``sensor_msgs/Imu``. Times are the messages'
header stamps. Out: the online estimate as ``nav_msgs/Odometry`` (frame ``map``, child
``base_link``) and the map priors as a ``visualization_msgs/MarkerArray``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .formats import FormatError, GpsFixes

ODOMETRY = "nav_msgs/msg/Odometry"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
IMU = "sensor_msgs/msg/Imu"
MARKERS = "visualization_msgs/msg/MarkerArray"
WHEEL = "geometry_msgs/msg/TwistStamped"  # a wheel-speed topic: twist.linear.x is the speed (m/s)


class BagError(FormatError):
    """A bag cannot be read, or lacks a topic of the right type (the message lists the bag's topics)."""


class BagKind(str, enum.Enum):
    """What a written bag is: ROS 2 with MCAP or SQLite storage, or ROS 1."""

    mcap = "mcap"
    sqlite3 = "sqlite3"
    ros1 = "ros1"

    @classmethod
    def for_path(cls, path: str | Path) -> BagKind:
        """What a bag written to ``path`` is: ``NAME.bag`` ROS 1, any other name a ROS 2 MCAP folder."""
        return cls.ros1 if Path(path).suffix == ".bag" else cls.mcap


@dataclass
class BagData:
    """What :func:`read_bag` found: the odometry (body convention), the fixes, the IMU samples."""

    t_s: np.ndarray
    poses: np.ndarray  # (N, 4, 4)
    gps: GpsFixes | None
    gps_without_fix: int  # NavSatFix messages with status −1, skipped
    imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # t, accel (N, 3), gyro (N, 3)
    camera_frame: bool  # the odometry's child frame was an optical (camera) frame
    wheel: tuple[np.ndarray, np.ndarray] | None = None  # t, speed (m/s)
    position_var_m2: np.ndarray | None = None  # per odometry message: mean of the x and y pose variances


def _stamp(msg) -> float:
    return float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)


def _quat_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not 0.9 <= n <= 1.1:
        raise BagError("an odometry orientation is not a unit quaternion")
    return Rotation.from_quat([qx / n, qy / n, qz / n, qw / n]).as_matrix()


def _is_optical(child_frame: str) -> bool:
    return "optical" in child_frame.lower()


def read_bag(path: str | Path, odometry_topic: str, gps_topic: str | None = None,
             imu_topic: str | None = None, wheel_topic: str | None = None) -> BagData:
    """Read the named topics of a ROS 1 or ROS 2 bag (:class:`BagError` on any problem)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag")
    pairs = [(odometry_topic, ODOMETRY)] + ([(gps_topic, NAVSATFIX)] if gps_topic else []) + (
        [(imu_topic, IMU)] if imu_topic else []) + ([(wheel_topic, WHEEL)] if wheel_topic else [])
    wanted = dict(pairs)
    try:
        with AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            topics = {c.topic: c.msgtype for c in reader.connections}
            for topic, msgtype in pairs:
                if topics.get(topic) != msgtype:
                    have = sorted(t for t, m in topics.items() if m == msgtype)
                    found = f"is {topics[topic]}" if topic in topics else "is not in the bag"
                    raise BagError(f"{p}: topic {topic} {found}; {msgtype} topics: {', '.join(have) or 'none'}")
            got = _collect(reader, wanted)
    except BagError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags' many reader errors: a truncated or foreign file
        why = str(exc).splitlines()[0] if str(exc) else ""
        raise BagError(f"{p}: cannot read the bag ({type(exc).__name__}: {why})") from None
    data = _assemble(p, got, odometry_topic, gps_topic, imu_topic)
    if wheel_topic:
        w = np.array(sorted(got[WHEEL]), dtype=float).reshape(-1, 2)
        data.wheel = (w[:, 0], w[:, 1])
    return data


def _collect(reader, wanted: dict[str, str]) -> dict:
    """The messages of the wanted topics, decoded into plain rows by type."""
    got: dict = {ODOMETRY: [], NAVSATFIX: [], IMU: [], WHEEL: [], "no_fix": 0, "camera": False}
    conns = [c for c in reader.connections if c.topic in wanted]
    for conn, _t, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.msgtype == ODOMETRY:
            got["camera"] = got["camera"] or _is_optical(msg.child_frame_id)
            q, pos = msg.pose.pose.orientation, msg.pose.pose.position
            m = np.eye(4)
            m[:3, :3] = _quat_matrix(q.x, q.y, q.z, q.w)
            m[:3, 3] = (pos.x, pos.y, pos.z)
            cov = msg.pose.covariance
            got[ODOMETRY].append((_stamp(msg), m, 0.5 * (float(cov[0]) + float(cov[7]))))
        elif conn.msgtype == NAVSATFIX:
            if msg.status.status < 0:
                got["no_fix"] += 1
                continue
            cov = np.asarray(msg.position_covariance, dtype=float)
            sigma = math.sqrt(0.5 * (cov[0] + cov[4])) if msg.position_covariance_type > 0 else math.nan
            got[NAVSATFIX].append((_stamp(msg), msg.latitude, msg.longitude, msg.altitude, sigma))
        elif conn.msgtype == WHEEL:
            got[WHEEL].append((_stamp(msg), msg.twist.linear.x))
        else:
            a, g = msg.linear_acceleration, msg.angular_velocity
            got[IMU].append((_stamp(msg), a.x, a.y, a.z, g.x, g.y, g.z))
    return got


def _assemble(p: Path, got: dict, odometry_topic: str, gps_topic: str | None, imu_topic: str | None) -> BagData:
    odo = sorted(got[ODOMETRY], key=lambda r: r[0])
    if len(odo) < 2:
        raise BagError(f"{p}: {odometry_topic} has {len(odo)} message(s); the engine needs at least two")
    t = np.array([r[0] for r in odo])
    if np.any(np.diff(t) <= 0):
        raise BagError(f"{p}: {odometry_topic} has two messages with the same header stamp")
    poses = np.array([r[1] for r in odo])
    var = np.array([r[2] for r in odo])
    if got["camera"]:
        from .replay import camera_to_body

        poses = camera_to_body(poses)
    gps = None
    if gps_topic:
        a = np.array(sorted(got[NAVSATFIX]), dtype=float).reshape(-1, 5)
        gps = GpsFixes(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4])
    imu = None
    if imu_topic:
        b = np.array(sorted(got[IMU]), dtype=float).reshape(-1, 7)
        imu = (b[:, 0], b[:, 1:4], b[:, 4:7])
    return BagData(t, poses, gps, got["no_fix"], imu, got["camera"],
                   position_var_m2=var if np.any(var > 0) and np.all(np.isfinite(var)) else None)


def sigma_per_m_from_covariance(poses: np.ndarray, position_var_m2: np.ndarray) -> float | None:
    """The odometry's σ per metre of a step (the engine's ``odometry_sigma_per_m``) from the growth
    of its published position variance: steps of length L with σ = s·L add s²·L² of variance each,
    so the variance grows by s²·L̄ per metre driven. None when it does not grow."""
    steps = np.hypot(*np.diff(poses[:, :2, 3], axis=0).T)
    driven = float(steps.sum())
    growth = float(position_var_m2[-1] - position_var_m2[0])
    if driven <= 0 or growth <= 0 or not np.any(steps > 0):
        return None
    mean_step = float(steps[steps > 0].mean())
    return math.sqrt(growth / driven / mean_step)


# ----------------------------------------------------------------------------- writing
def _writer(path: Path, kind: BagKind):
    if kind is BagKind.ros1:
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(path)
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    plugin = StoragePlugin.MCAP if kind is BagKind.mcap else StoragePlugin.SQLITE3
    return Writer2(path, version=9, storage_plugin=plugin)


def _time(ts, t: float):
    sec = math.floor(t)
    return ts.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def _make(cls, **fields):
    """A message of ``cls`` from the fields its ROS version has (ROS 1 and ROS 2 differ a little)."""
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in fields.items() if k in names})


def _header(ts, t: float, frame: str):
    return _make(ts.types["std_msgs/msg/Header"], seq=0, stamp=_time(ts, t), frame_id=frame)


def write_bag(path: str | Path, kind: BagKind | str, odometry: tuple[np.ndarray, np.ndarray] | None = None,
              gps: GpsFixes | None = None, imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
              odometry_topic: str = "/odom", gps_topic: str = "/gps/fix", imu_topic: str = "/imu",
              frame: str = "odom", child_frame: str = "base_link", covariances: np.ndarray | None = None,
              markers: tuple[str, np.ndarray, np.ndarray] | None = None,
              wheel: tuple[np.ndarray, np.ndarray] | None = None, wheel_topic: str = "/wheel_speed") -> Path:
    """A bag of ``kind`` with the given streams: odometry (t, (N, 4, 4) poses) as nav_msgs/Odometry
    (``covariances``: (N, 6, 6), else zero), fixes as NavSatFix (σ → a diagonal covariance, a NaN σ
    → covariance type unknown), IMU samples; ``markers`` (topic, t, (M, 3) positions) as one
    MarkerArray of spheres."""
    from rosbags.typesys import Stores, get_typestore

    kind = BagKind(kind)
    ts = get_typestore(Stores.ROS1_NOETIC if kind is BagKind.ros1 else Stores.ROS2_HUMBLE)
    streams = []
    if odometry is not None:
        streams.append((odometry_topic, ODOMETRY, _odometry_msgs(ts, odometry, frame, child_frame, covariances)))
    if gps is not None:
        streams.append((gps_topic, NAVSATFIX, _gps_msgs(ts, gps)))
    if imu is not None:
        streams.append((imu_topic, IMU, _imu_msgs(ts, imu)))
    if wheel is not None:
        streams.append((wheel_topic, WHEEL, _wheel_msgs(ts, wheel)))
    if markers is not None:
        topic, mt, xyz = markers
        items = [_sphere(ts, i, float(t), p_) for i, (t, p_) in enumerate(zip(mt, xyz))]
        streams.append((topic, MARKERS, [(float(mt[-1]) if len(mt) else 0.0, ts.types[MARKERS](markers=items))]))
    p = Path(path)
    with _writer(p, kind) as w:
        out = []
        for topic, msgtype, msgs in streams:
            conn = w.add_connection(topic, msgtype, typestore=ts)
            out += [(int(round(t * 1e9)), conn, msg) for t, msg in msgs]
        for ns, conn, msg in sorted(out, key=lambda r: r[0]):
            data = ts.serialize_ros1(msg, conn.msgtype) if kind is BagKind.ros1 else ts.serialize_cdr(msg, conn.msgtype)
            w.write(conn, ns, data)
    return p


def _odometry_msgs(ts, odometry, frame: str, child_frame: str, covariances) -> list:
    from scipy.spatial.transform import Rotation

    T = ts.types
    v3 = T["geometry_msgs/msg/Vector3"]
    still = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=v3(x=0.0, y=0.0, z=0.0), angular=v3(x=0.0, y=0.0, z=0.0)),
        covariance=np.zeros(36))
    out = []
    for i, (t, m) in enumerate(zip(*odometry)):
        qx, qy, qz, qw = Rotation.from_matrix(m[:3, :3]).as_quat()
        cov = np.zeros(36) if covariances is None else np.asarray(covariances[i], float).ravel()
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
            covariance=cov)
        out.append((float(t), T[ODOMETRY](header=_header(ts, t, frame), child_frame_id=child_frame, pose=pose,
                                          twist=still)))
    return out


def _gps_msgs(ts, gps: GpsFixes) -> list:
    T = ts.types
    out = []
    for t, lat, lon, alt, sig in zip(gps.t_s, gps.lat_deg, gps.lon_deg, gps.alt_m, gps.sigma_m):
        known = math.isfinite(sig)
        cov = np.diag([sig * sig, sig * sig, (2 * sig) ** 2]).ravel() if known else np.zeros(9)
        status = T["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
        out.append((float(t), T[NAVSATFIX](header=_header(ts, t, "gps"), status=status, latitude=lat, longitude=lon,
                                           altitude=alt if math.isfinite(alt) else 0.0, position_covariance=cov,
                                           position_covariance_type=2 if known else 0)))
    return out


def _wheel_msgs(ts, wheel) -> list:
    T = ts.types
    v3 = T["geometry_msgs/msg/Vector3"]
    return [(float(t), T[WHEEL](header=_header(ts, t, "base_link"),
                                twist=T["geometry_msgs/msg/Twist"](linear=v3(x=float(v), y=0.0, z=0.0),
                                                                   angular=v3(x=0.0, y=0.0, z=0.0))))
            for t, v in zip(*wheel)]


def _imu_msgs(ts, imu) -> list:
    T = ts.types
    v3, q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    return [(float(t), T[IMU](header=_header(ts, t, "imu"), orientation=q(x=0.0, y=0.0, z=0.0, w=1.0),
                              orientation_covariance=np.r_[-1.0, np.zeros(8)],
                              angular_velocity=v3(x=g[0], y=g[1], z=g[2]), angular_velocity_covariance=np.zeros(9),
                              linear_acceleration=v3(x=a[0], y=a[1], z=a[2]),
                              linear_acceleration_covariance=np.zeros(9)))
            for t, a, g in zip(*imu)]


def _sphere(ts, i: int, t: float, xyz):
    T = ts.types
    return _make(T["visualization_msgs/msg/Marker"],
        header=_header(ts, t, "map"), ns="map_priors", id=i, type=2, action=0,
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
        scale=T["geometry_msgs/msg/Vector3"](x=1.0, y=1.0, z=1.0),
        color=T["std_msgs/msg/ColorRGBA"](r=1.0, g=0.2, b=0.2, a=0.8),
        lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False, points=[], colors=[],
        texture_resource="", uv_coordinates=[], text="", mesh_resource="", mesh_use_embedded_materials=False,
        **({} if "sensor_msgs/msg/CompressedImage" not in T or "visualization_msgs/msg/MeshFile" not in T else {
            "texture": T["sensor_msgs/msg/CompressedImage"](header=_header(ts, t, "map"), format="",
                                                             data=np.zeros(0, dtype=np.uint8)),
            "mesh_file": T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8))}))
