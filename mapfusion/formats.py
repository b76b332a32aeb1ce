"""File formats (DESIGN "File formats", contract): TUM trajectories.

TUM: one pose a line, ``t tx ty tz qx qy qz qw``, ``#`` comments, readable by evo.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import InputError


class FormatError(InputError):
    """A data file is malformed; the message names the file and the line."""


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
    lines = [f"# {ln}" for ln in header.splitlines()] + ["# t tx ty tz qx qy qz qw"]
    for t, (x, y, z), (qx, qy, qz, qw) in zip(t_s, xyz_m, q_xyzw):
        lines.append(f"{t:.6f} {x:.4f} {y:.4f} {z:.4f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}")
    p.write_text("\n".join(lines) + "\n")
    return p


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(t (N,), xyz (N, 3), q_xyzw (N, 4))``.

    A line with other than 8 numbers, a non-finite value or a time not after the previous one
    raises :class:`FormatError` naming the file and the line.
    """
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{p}: no such file")
    rows = []
    last_t = -math.inf
    with open(p, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != 8:
                raise FormatError(f"{p}:{lineno}: expected 8 numbers (t tx ty tz qx qy qz qw), got {len(parts)}")
            try:
                vals = [float(v) for v in parts]
            except ValueError:
                raise FormatError(f"{p}:{lineno}: not a number in {s[:60]!r}") from None
            if not all(math.isfinite(v) for v in vals):
                raise FormatError(f"{p}:{lineno}: NaN or infinite value")
            if vals[0] <= last_t:
                raise FormatError(f"{p}:{lineno}: time {vals[0]} does not increase (previous {last_t})")
            last_t = vals[0]
            rows.append(vals)
    if not rows:
        raise FormatError(f"{p}: no poses in the file")
    a = np.asarray(rows)
    return a[:, 0], a[:, 1:4], a[:, 4:8]
