"""File formats (DESIGN "File formats", contract).

- TUM trajectory: one pose a line, ``t tx ty tz qx qy qz qw``, ``#`` comments (readable by evo).
- GPS: CSV with header ``t,lat,lon,alt,sigma_m``; ``alt`` and ``sigma_m`` may be empty.
- IMU: CSV with header ``t,ax,ay,az,gx,gy,gz`` (body frame, m/s², rad/s).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError


class FormatError(InputError):
    """A data file is malformed; the message names the file and the line."""


#: No trajectory of a drive on Earth has a coordinate beyond this (10,000 km); a larger one is a
#: broken file, and 1e308 would overflow the arithmetic that follows.
MAX_COORDINATE_M = 1.0e7


def read_text(path: str | Path, what: str = "file", error: type[InputError] = FormatError) -> str:
    """A text file's contents, strictly UTF-8: a missing file, a directory, an unreadable or a
    binary/non-UTF-8 file raises ``error`` (a :class:`FormatError` by default) naming it."""
    return "".join(line for _, line in _text_lines(path, what, error))


def read_toml(path: str | Path, what: str = "TOML file", error: type[InputError] = FormatError) -> dict:
    """A TOML file as a mapping; any problem (see :func:`read_text`, a syntax error) raises ``error``."""
    import tomllib

    text = read_text(path, what, error)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML ({exc})") from None


def yaw_to_quaternion(yaw_rad: np.ndarray) -> np.ndarray:
    """(N,) yaw → (N, 4) quaternions (qx, qy, qz, qw) of a level body."""
    half = 0.5 * np.asarray(yaw_rad, dtype=float)
    z = np.zeros_like(half)
    return np.column_stack([z, z, np.sin(half), np.cos(half)])


def quaternion_to_yaw(q_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (qx, qy, qz, qw) → (N,) yaw (ZYX convention)."""
    q = np.asarray(q_xyzw, dtype=float)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def write_tum(path: str | Path, t_s: np.ndarray, xyz_m: np.ndarray, q_xyzw: np.ndarray, header: str = "") -> Path:
    """Write a TUM trajectory. Times with 6 decimals, positions with 4, quaternions with 9."""
    p = Path(path)
    t_s = np.asarray(t_s, dtype=float)
    xyz_m = np.asarray(xyz_m, dtype=float).reshape(-1, 3)
    q_xyzw = np.asarray(q_xyzw, dtype=float).reshape(-1, 4)
    if not (len(t_s) == len(xyz_m) == len(q_xyzw)):
        raise ValueError("write_tum: t, xyz and q must have the same length")
    lines = _tum_header(header) + _tum_lines(t_s, xyz_m, q_xyzw)
    p.write_text("\n".join(lines) + "\n")
    return p


def _tum_header(header: str) -> list[str]:
    return [f"# {ln}" for ln in header.splitlines()] + ["# t tx ty tz qx qy qz qw"]


def _tum_lines(t_s, xyz_m, q_xyzw) -> list[str]:
    return [f"{t:.6f} {x:.4f} {y:.4f} {z:.4f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}"
            for t, (x, y, z), (qx, qy, qz, qw) in zip(t_s, xyz_m, q_xyzw)]


class TumWriter:
    """A TUM trajectory written as it is produced (the lines :func:`write_tum` writes), into a
    temporary file renamed to ``path`` by :meth:`commit`; :meth:`discard` leaves nothing."""

    def __init__(self, path: str | Path, header: str = "") -> None:
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.partial")
        self._f = open(self._tmp, "w")
        self._f.write("\n".join(_tum_header(header)) + "\n")
        self.count = 0

    def write(self, t_s, xyz_m, q_xyzw) -> None:
        lines = _tum_lines(np.asarray(t_s, dtype=float), np.asarray(xyz_m, dtype=float).reshape(-1, 3),
                           np.asarray(q_xyzw, dtype=float).reshape(-1, 4))
        if lines:
            self._f.write("\n".join(lines) + "\n")
            self.count += len(lines)

    def commit(self) -> Path:
        self._f.close()
        self._tmp.replace(self.path)
        return self.path

    def discard(self) -> None:
        self._f.close()
        self._tmp.unlink(missing_ok=True)


def _text_lines(path: str | Path, what: str, error: type[InputError] = FormatError):
    """A text file's lines, streamed and strictly UTF-8: (line number, line); a missing file, a
    directory, a binary or non-UTF-8 file raises ``error`` naming it (and the line)."""
    p = Path(path)
    if not p.exists():
        raise error(f"{p}: no such {what}")
    if p.is_dir():
        raise error(f"{p}: is a directory, not a {what}")
    lineno = 0
    try:
        with open(p, encoding="utf-8", errors="strict") as f:
            for lineno, line in enumerate(f, start=1):
                if "\0" in line:
                    raise error(f"{p}:{lineno}: a binary file, not a {what}")
                yield lineno, line
    except UnicodeDecodeError:
        raise error(f"{p}:{lineno + 1}: not UTF-8 text, not a {what}") from None
    except OSError as exc:
        raise error(f"{p}: cannot read ({exc.strerror})") from None


def numeric_rows(path: str | Path, columns: int | None, what: str, increasing: bool = True, comma_ok: bool = False):
    """Rows of whitespace-separated numbers from a text file (streamed), with ``#`` comments and
    blank lines skipped: ``(line number, values)``. A row with other than ``columns`` numbers (when
    given), a non-number, NaN or infinity, or (``increasing``) a first value not above the previous
    one raises :class:`FormatError` naming the file and line; ``what`` describes a row."""
    p = Path(path)
    last = -math.inf
    for lineno, line in _text_lines(p, "text file of numbers"):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = (s.replace(",", " ") if comma_ok else s).split()
        if columns is not None and len(parts) != columns:
            raise FormatError(f"{p}:{lineno}: expected {columns} numbers ({what}), got {len(parts)}")
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise FormatError(f"{p}:{lineno}: not a number in {s[:60]!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise FormatError(f"{p}:{lineno}: NaN or infinite value")
        if increasing:
            if vals[0] <= last:
                raise FormatError(f"{p}:{lineno}: time {vals[0]} does not increase (previous {last})")
            last = vals[0]
        yield lineno, vals


def tum_rows(path: str | Path):
    """The checked rows of a TUM trajectory, streamed: ``t tx ty tz qx qy qz qw`` lists."""
    for lineno, v in numeric_rows(path, 8, "t tx ty tz qx qy qz qw", comma_ok=True):
        if max(abs(c) for c in v[1:4]) > MAX_COORDINATE_M:
            raise FormatError(f"{path}:{lineno}: a coordinate beyond {MAX_COORDINATE_M:g} m")
        if not 0.9 <= math.sqrt(sum(c * c for c in v[4:8])) <= 1.1:
            raise FormatError(f"{path}:{lineno}: the quaternion qx qy qz qw is not of unit length")
        yield v


def _tum_fast(p: Path) -> np.ndarray | None:
    """A TUM file parsed in one numpy call when every row passes :func:`tum_rows`'s checks (the same
    values: both parse with correct rounding); None when any might not, or on anything unusual."""
    try:
        data = p.read_bytes()
        if b"\0" in data or b"," in data:
            return None
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (an empty file warns; it is reported by the checking parser)
            a = np.loadtxt(io.StringIO(data.decode("utf-8")), dtype=float, comments="#", ndmin=2)
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if a.shape[1:] != (8,) or not len(a) or not np.isfinite(a).all() or not np.all(np.diff(a[:, 0]) > 0):
        return None
    q = np.sqrt(np.sum(a[:, 4:8] ** 2, axis=1))
    if np.abs(a[:, 1:4]).max() > MAX_COORDINATE_M or not np.all((q > 0.9 + 1e-9) & (q < 1.1 - 1e-9)):
        return None
    return a


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(t (N,), xyz (N, 3), q_xyzw (N, 4))``.

    A line with other than 8 numbers, a non-finite value, a time not after the previous one, a
    coordinate beyond 10⁷ m or a quaternion not of unit length raises :class:`FormatError` naming
    the file and the line.
    """
    a = _tum_fast(Path(path))
    if a is None:  # something to report (or commas): the checking parser names the line
        a = np.array(list(tum_rows(path)), dtype=float).reshape(-1, 8)
    if not len(a):
        raise FormatError(f"{path}: no poses in the file")
    return a[:, 0], a[:, 1:4], a[:, 4:8]


def kitti_rows(path: str | Path):
    """The checked rows of a KITTI poses file, streamed: 12 numbers, the top 3×4 of T_world_cam."""
    for lineno, v in numeric_rows(path, 12, "a KITTI pose: the top 3×4 of T_world_cam", increasing=False):
        if max(abs(v[3]), abs(v[7]), abs(v[11])) > MAX_COORDINATE_M:
            raise FormatError(f"{path}:{lineno}: a coordinate beyond {MAX_COORDINATE_M:g} m")
        r = np.asarray(v).reshape(3, 4)[:, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=0.05):
            raise FormatError(f"{path}:{lineno}: the 3×3 part is not a rotation")
        yield v


def kitti_to_matrices(rows) -> np.ndarray:
    """KITTI rows (N, 12) → (N, 4, 4) poses."""
    a = np.asarray(rows, dtype=float).reshape(-1, 12)
    m = np.tile(np.eye(4), (len(a), 1, 1))
    m[:, :3, :4] = a.reshape(-1, 3, 4)
    return m


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """KITTI odometry poses: 12 numbers a line (the top 3×4 of T_world_cam), → (N, 4, 4)."""
    rows = list(kitti_rows(path))
    if not rows:
        raise FormatError(f"{path}: no poses in the file")
    return kitti_to_matrices(rows)


def read_times(path: str | Path) -> np.ndarray:
    """One timestamp a line (KITTI ``times.txt``); strictly increasing."""
    return np.asarray([v[0] for _, v in numeric_rows(path, 1, "one time in seconds")])


def matrices_to_tum(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) poses → (xyz (N, 3), q_xyzw (N, 4))."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, dtype=float)
    return poses[:, :3, 3], Rotation.from_matrix(poses[:, :3, :3]).as_quat()


def tum_to_matrices(xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """(xyz (N, 3), q_xyzw (N, 4)) → (N, 4, 4) poses (quaternions normalised)."""
    from scipy.spatial.transform import Rotation

    n = len(xyz)
    m = np.tile(np.eye(4), (n, 1, 1))
    q = np.asarray(q_xyzw, dtype=float)
    norm = np.linalg.norm(q, axis=1)
    if np.any(norm < 1e-9):
        raise FormatError("a quaternion of zero length")
    m[:, :3, :3] = Rotation.from_quat(q / norm[:, None]).as_matrix()
    m[:, :3, 3] = xyz
    return m


GPS_HEADER = ("t", "lat", "lon", "alt", "sigma_m")
#: The largest GPS σ a file may give: beyond the size of the Earth a σ says nothing.
MAX_GPS_SIGMA_M = 1e7
IMU_HEADER = ("t", "ax", "ay", "az", "gx", "gy", "gz")
WHEEL_HEADER = ("t", "speed_mps")
#: A wheel speed above this is no road vehicle's (m/s): the file is not a wheel-speed log.
MAX_WHEEL_SPEED_MPS = 150.0


@dataclass
class GpsFixes:
    """GPS fixes as read from a CSV: NaN where ``alt`` or ``sigma_m`` was empty."""

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    sigma_m: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)

    def until(self, t_end_s: float) -> GpsFixes:
        """The fixes at or before ``t_end_s``."""
        keep = self.t_s <= t_end_s
        return GpsFixes(self.t_s[keep], self.lat_deg[keep], self.lon_deg[keep], self.alt_m[keep], self.sigma_m[keep])


def write_gps_csv(path: str | Path, t_s, lat_deg, lon_deg, alt_m=None, sigma_m=None) -> Path:
    p = Path(path)
    n = len(t_s)
    alt: list[Any] = [None] * n if alt_m is None else list(alt_m)
    sig: list[Any] = [None] * n if sigma_m is None else list(sigma_m)
    with open(p, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(GPS_HEADER)
        for i in range(n):
            w.writerow([f"{t_s[i]:.6f}", f"{lat_deg[i]:.9f}", f"{lon_deg[i]:.9f}",
                        "" if alt[i] is None or not math.isfinite(alt[i]) else f"{alt[i]:.3f}",
                        "" if sig[i] is None or not math.isfinite(sig[i]) else f"{sig[i]:.3f}"])
    return p


def _csv_rows(path: Path, header: tuple[str, ...], optional: set[str]):
    # streamed: an IMU file of a long drive is never held whole
    reader = csv.reader(line for _, line in _text_lines(path, "CSV file"))
    try:
        head = [h.strip() for h in next(reader)]
    except StopIteration:
        raise FormatError(f"{path}: empty file") from None
    if tuple(head[: len(header)]) != header:
        raise FormatError(f"{path}:1: header must start with {','.join(header)}, got {','.join(head)}")
    last_t = -math.inf
    for lineno, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
            continue
        if len(row) < len(header):
            raise FormatError(f"{path}:{lineno}: expected {len(header)} columns, got {len(row)}")
        vals = []
        for name, cell in zip(header, row):
            cell = cell.strip()
            if cell == "" and name in optional:
                vals.append(math.nan)
                continue
            try:
                v = float(cell)
            except ValueError:
                raise FormatError(f"{path}:{lineno}: {name} is not a number: {cell!r}") from None
            vals.append(v)
        if vals[0] <= last_t:
            raise FormatError(f"{path}:{lineno}: time {vals[0]} does not increase (previous {last_t})")
        last_t = vals[0]
        yield lineno, vals


def read_gps_csv(path: str | Path) -> GpsFixes:
    """Read a GPS CSV. Malformed lines and time going backwards raise :class:`FormatError` with
    file and line. Non-finite values are kept (the engine counts and rejects them)."""
    p = Path(path)
    rows = []
    for lineno, vals in _csv_rows(p, GPS_HEADER, {"alt", "sigma_m"}):
        lat, lon, sigma = vals[1], vals[2], vals[4]
        if (math.isfinite(lat) and not -90.0 <= lat <= 90.0) or (math.isfinite(lon) and not -180.0 <= lon <= 180.0):
            raise FormatError(f"{p}:{lineno}: lat must be within ±90° and lon within ±180°, got {lat:g}, {lon:g}")
        # an empty σ means "the configured one"; a σ given must be one (never silently replaced)
        if not math.isnan(sigma) and not 0.0 < sigma <= MAX_GPS_SIGMA_M:
            raise FormatError(f"{p}:{lineno}: sigma_m must be > 0 and at most {MAX_GPS_SIGMA_M:g} m, got {sigma:g} "
                              "(leave it empty for the configured σ)")
        rows.append(vals)
    a = np.asarray(rows, dtype=float).reshape(-1, 5)
    return GpsFixes(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4])


def write_imu_csv(path: str | Path, t_s, accel_mps2, gyro_radps) -> Path:
    """``imu.csv``: one %-format over each row (3.6× the csv module's speed, the same text; issue 21)."""
    p = Path(path)
    rows = np.column_stack([np.asarray(t_s, dtype=float), np.asarray(accel_mps2, dtype=float).reshape(-1, 3),
                            np.asarray(gyro_radps, dtype=float).reshape(-1, 3)]).tolist()
    fmt = "%.4f,%.6f,%.6f,%.6f,%.7f,%.7f,%.7f\n"
    with open(p, "w") as f:
        f.write(",".join(IMU_HEADER) + "\n")
        f.writelines(fmt % tuple(r) for r in rows)
    return p


def check_imu_csv(path: str | Path) -> int:
    """Read an IMU CSV through (streamed, nothing kept), raising :class:`FormatError` as
    :func:`read_imu_csv` does; returns the number of samples."""
    return sum(1 for _ in _csv_rows(Path(path), IMU_HEADER, set()))


def read_imu_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an IMU CSV: ``(t (N,), accel (N, 3), gyro (N, 3))``."""
    p = Path(path)
    rows = [vals for _, vals in _csv_rows(p, IMU_HEADER, set())]
    a = np.asarray(rows, dtype=float).reshape(-1, 7)
    return a[:, 0], a[:, 1:4], a[:, 4:7]


def write_wheel_csv(path: str | Path, t_s, speed_mps) -> Path:
    """``wheel.csv``: ``t,speed_mps`` (seconds, metres per second; forward speed, ≥ 0)."""
    p = Path(path)
    with open(p, "w") as f:
        f.write(",".join(WHEEL_HEADER) + "\n")
        f.writelines(f"{t:.4f},{v:.4f}\n" for t, v in zip(t_s, speed_mps))
    return p


def read_wheel_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a wheel-speed CSV: ``(t (N,), speed_mps (N,))``. A speed that is negative, non-finite or
    beyond any road vehicle's raises :class:`FormatError` with file and line."""
    p = Path(path)
    rows = []
    for lineno, vals in _csv_rows(p, WHEEL_HEADER, set()):
        if not 0.0 <= vals[1] <= MAX_WHEEL_SPEED_MPS:
            raise FormatError(f"{p}:{lineno}: speed_mps must be within 0–{MAX_WHEEL_SPEED_MPS:g} m/s, got {vals[1]:g}")
        rows.append(vals)
    a = np.asarray(rows, dtype=float).reshape(-1, 2)
    if not len(a):
        raise FormatError(f"{p}: no wheel-speed samples in the file")
    return a[:, 0], a[:, 1]
