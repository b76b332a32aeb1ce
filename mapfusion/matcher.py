"""Matching a pose to the road map (paper III.B, DESIGN "The method" item 2).

D = E + w·A, where E is the planar Euclidean distance to a way-point, A the rotation angle in
degrees between the pose's orientation and the way-point's orientation,
A = arccos(2⟨q_P, q_R⟩² − 1) — for orientations that differ only in yaw this is |Δyaw| in
[0, 180] — and w (metres per degree, default 1) weighs direction against distance. Both travel
directions of a two-way road are candidates, so its best direction has A ≤ 90°; a one-way road
offers only the direction one may drive it (``RoadMap.legal_cos``/``legal_sin``, ``two_way_sign``),
so a vehicle is never matched against the traffic of a one-way carriageway (issue 16: a dual
carriageway's other half, a few metres away, was the wrong association that held estimates off
their road). The lateral distance is L = |y of R⁻¹P|, R being the matched map pose.

Everything here is pure and vectorised with numpy: no Python loop per candidate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .geometry import as_complex, fast_clip

if TYPE_CHECKING:
    from .roadmap import RoadMap

DEFAULT_RADIUS_M = 20.0
DEFAULT_ANGLE_WEIGHT_M_PER_DEG = 1.0
#: The batch matcher's k nearest way-points per pass: 48 first settles ≥ 90% of poses near roads
#: (3 m, 0.2 rad off) where 24 settled 49%, and is faster overall (``mapfusion bench``).
FIRST_PASS_K = (48, 128)


@dataclass(frozen=True)
class Match:
    """The closest map pose to a vehicle pose by D = E + w·A.

    ``x_m``, ``y_m``: the matched way-point; ``yaw_rad``: the road's heading in the matched
    direction of travel; ``reversed``: the match runs against the way's drawing direction.
    ``lateral_m`` (L, ≥ 0) and ``longitudinal_m`` (signed, along the matched direction) are the
    pose's offset in the map pose's frame; ``along_m`` is the pose's position along its edge (or
    join curve) measured in the drawing direction. ``distance_m`` (E), ``angle_deg`` (A, in
    [0, 180]) and ``cost`` (D = E + w·A) are the matching terms.
    """

    index: int
    x_m: float
    y_m: float
    yaw_rad: float
    reversed: bool
    way_id: int
    edge: int
    is_join: bool
    lanes: int
    lateral_m: float
    signed_lateral_m: float
    longitudinal_m: float
    along_m: float
    distance_m: float
    angle_deg: float
    cost: float


_clip = fast_clip  # (the matcher's name for it)
_TWO_PI = 2.0 * math.pi
_DEG_PER_RAD = 180.0 / math.pi


def _new_match(**values) -> Match:
    """A Match from every one of its fields by name, without the frozen dataclass's __init__ (sixteen
    ``object.__setattr__`` calls, a tenth of a single match's cost, issue 21); the instance is the same."""
    m = object.__new__(Match)
    m.__dict__.update(values)
    return m


def check_pose_args(x: float, y: float, yaw: float, radius: float) -> None:
    """ValueError naming the argument when a coordinate, the yaw or the radius is unusable."""
    for name, v in (("x", x), ("y", y), ("yaw", yaw)):
        if not math.isfinite(v):
            raise ValueError(f"match: {name} must be finite, got {v!r}")
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"match: radius must be a finite number > 0, got {radius!r}")


def angle_deg(yaw_a_rad, yaw_b_rad):
    """Rotation angle A in degrees between two planar orientations: arccos(2⟨q_a, q_b⟩² − 1).

    For yaw-only quaternions ⟨q_a, q_b⟩ = cos(Δ/2), so A = arccos(cos Δ) = |wrap(Δ)| ∈ [0, 180].
    Computed through atan2 to stay exact near 0 and 180 (arccos loses half the digits there).
    """
    d = np.asarray(yaw_a_rad) - np.asarray(yaw_b_rad)
    return np.degrees(np.abs(np.arctan2(np.sin(d), np.cos(d))))


def quaternion_angle_deg(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """The paper's A = arccos(2⟨q_a, q_b⟩² − 1) in degrees, for unit quaternions (…, 4)."""
    dot = np.sum(np.asarray(q_a) * np.asarray(q_b), axis=-1)
    return np.degrees(np.arccos(np.clip(2.0 * dot * dot - 1.0, -1.0, 1.0)))


def match_candidates(
    x: float,
    y: float,
    yaw: float,
    cand_xy: np.ndarray,
    cand_cos: np.ndarray,
    cand_sin: np.ndarray,
    angle_weight_m_per_deg: float = DEFAULT_ANGLE_WEIGHT_M_PER_DEG,
    cand_sign: np.ndarray | None = None,
) -> tuple[int, bool, float, float, float]:
    """Best candidate by D = E + w·A over the legal travel directions.

    Candidates are given by position, the cosine and sine of their heading and ``cand_sign``: -1
    where both directions are legal (the default), +1 where only the given heading is. The better
    of a two-way road's directions has A = arccos(|cos Δ|), reversed when cos Δ < 0; a one-way
    road's A = arccos(cos Δ), never reversed. Returns ``(position in candidates, reversed, E, A, D)``;
    the caller guarantees at least one candidate. Ties go to the earlier candidate, in the heading's
    direction.
    """
    sign = np.full(len(cand_cos), -1.0) if cand_sign is None else cand_sign
    found = _best(as_complex(cand_xy), cand_cos, cand_sin, sign, x, y, yaw, angle_weight_m_per_deg, math.inf)
    assert found is not None  # (no radius: every candidate counts)
    return found


def match(
    road: RoadMap,
    x: float,
    y: float,
    yaw: float,
    radius: float = DEFAULT_RADIUS_M,
    angle_weight_m_per_deg: float = DEFAULT_ANGLE_WEIGHT_M_PER_DEG,
    candidates: np.ndarray | None = None,
) -> Match | None:
    """The best way-point within ``radius`` of (x, y) by D = E + w·A, or None.

    ``candidates`` (way-point indices) restricts the search, e.g. to the roads the graph
    connects to the current one; by default every way-point within the radius competes.
    Raises ValueError naming the argument for a non-finite x, y or yaw, or a radius ≤ 0.
    """
    check_pose_args(x, y, yaw, radius)
    if candidates is None:  # the cell index: the disc's rows of cells are contiguous slices
        cells = road.cells
        sl = cells.slices(x, y, radius)
        if not sl:
            return None
        b = cells.gather(cells.block, sl)
        found = _best(cells.gather(cells.z, sl), b[0], b[1], b[2], x, y, yaw, angle_weight_m_per_deg, radius)
        if found is None:
            return None
        k, rev, e, a, d = found
        return _make_match(road, cells.point_of(sl, k), rev, x, y, e, a, d)
    idx = np.asarray(candidates, dtype=np.intp)
    if idx.size == 0:
        return None
    k, rev, e, a, d = match_candidates(
        x, y, yaw, road.xy_m[idx], road.legal_cos[idx], road.legal_sin[idx], angle_weight_m_per_deg,
        road.two_way_sign[idx]
    )
    return _make_match(road, int(idx[k]), rev, x, y, e, a, d)


def lateral_bound_ok(m: Match, pose_matrix: np.ndarray, width_m: float, centre_m: float = 0.0) -> bool:
    """True when :func:`map_pose`'s signed lateral offset for this pose is surely within ``width_m`` of
    ``centre_m`` (left positive) — decided without building R_t. R_t shares the pose's pitch and roll, so the
    offset is cos(roll)·l + sin(roll)·sin(pitch)·s with l, s the match's lateral and longitudinal offsets; the
    margin covers rounding."""
    pitch = math.asin(max(-1.0, min(1.0, -float(pose_matrix[2, 0]))))
    roll = math.atan2(float(pose_matrix[2, 1]), float(pose_matrix[2, 2]))
    lat = math.cos(roll) * m.signed_lateral_m + math.sin(roll) * math.sin(pitch) * m.longitudinal_m
    return abs(lat - centre_m) <= width_m - 1e-9 * (1.0 + width_m + abs(m.longitudinal_m) + abs(centre_m))


def _best(pz: np.ndarray, c: np.ndarray, s: np.ndarray, sign: np.ndarray, x: float, y: float,
          yaw: float, w: float, radius: float) -> tuple[int, bool, float, float, float] | None:
    """The best of points given as positions (complex, x + iy), heading and sign arrays
    (:func:`match_candidates`) by D = E + w·A over their legal travel directions, those farther than
    ``radius`` left out: ``(position, reversed against the heading, E, A, D)``, or None when every one
    is. Ties go to the earlier point."""
    # (|z - p|: numpy's complex absolute value, within 2 units in the last place of np.hypot's distance,
    # in two calls where hypot takes three and is twice as slow per point, issue 21)
    e = np.abs(pz - complex(x, y))
    cos_d = c * math.cos(yaw)
    cos_d += s * math.sin(yaw)
    a = sign * cos_d
    np.maximum(a, cos_d, out=a)  # |cos Δ| where both directions are legal (sign -1), cos Δ where one is
    _clip(a, -1.0, 1.0, out=a)
    np.arccos(a, out=a)
    a *= _DEG_PER_RAD  # (np.degrees' own product, without its keyword call)
    d = a + e if w == 1.0 else a * w + e  # (a · 1 is a: the default weight saves a pass)
    k = int(d.argmin())
    if e[k] > radius:  # the best lies outside the disc (rare: only when nothing inside matches well)
        d[e > radius] = np.inf
        k = int(d.argmin())
        if d[k] == math.inf:
            return None
    # (.item: Python scalars without a numpy scalar between, the same values)
    return k, cos_d.item(k) < 0.0 and sign.item(k) < 0.0, e.item(k), a.item(k), d.item(k)


def _make_match(road: RoadMap, i: int, rev: bool, x: float, y: float, e: float, a: float, d: float) -> Match:
    # (.item: a Python scalar straight from the array, the same value as float()/int() of an element)
    xy = road.xy_m
    px, py = xy.item(i, 0), xy.item(i, 1)
    if road.against_drawing.item(i):  # (rev came against the legal heading, which is the drawing's reverse)
        rev = not rev
    road_yaw = road.yaw_rad.item(i)
    if rev:
        road_yaw += math.pi
    road_yaw = (road_yaw + math.pi) % _TWO_PI - math.pi
    dx, dy = x - px, y - py  # the pose's offset in the map pose's frame: (longitudinal, signed lateral)
    c, s = math.cos(road_yaw), math.sin(road_yaw)
    lon, lat = c * dx + s * dy, -s * dx + c * dy
    way = road.way_index.item(i)
    edge = road.edge.item(i)
    return _new_match(index=i, x_m=px, y_m=py, yaw_rad=road_yaw, reversed=rev, way_id=road.way_ids.item(way),
                      edge=edge, is_join=edge < 0, lanes=road.way_lanes.item(way), lateral_m=abs(lat),
                      signed_lateral_m=lat, longitudinal_m=lon, along_m=road.s_m.item(i) + (-lon if rev else lon),
                      distance_m=e, angle_deg=a, cost=d)


def _match_k(road: RoadMap, x, y, c, s, radius: float, w: float, k: int):
    """Best of each pose's k nearest way-points within the radius, and whether that is exact."""
    n = len(x)
    dist, nn = road.tree.query(np.column_stack([x, y]), k=k, distance_upper_bound=radius)
    dist = dist.reshape(n, k)
    nn = nn.reshape(n, k)
    valid = np.isfinite(dist)
    nn = np.where(valid, nn, 0)
    cos_d = road.legal_cos[nn] * c[:, None] + road.legal_sin[nn] * s[:, None]
    sign = road.two_way_sign[nn]
    a = np.degrees(np.arccos(np.clip(np.maximum(sign * cos_d, cos_d), -1.0, 1.0)))
    d = np.where(valid, dist + w * a, np.inf)
    best = np.argmin(d, axis=1)
    rows = np.arange(n)
    cost = d[rows, best]
    # a way-point beyond the k nearest has D ≥ E ≥ the k-th distance: the best is exact when its
    # D does not exceed that distance, or when fewer than k way-points lie within the radius
    exact = ~valid[:, -1] | (cost <= dist[:, -1])
    return {
        "index": np.where(valid[rows, best], nn[rows, best], -1),
        "reversed": ((cos_d[rows, best] < 0.0) & (sign[rows, best] < 0.0)) ^ road.against_drawing[nn[rows, best]],
        "distance_m": dist[rows, best],
        "angle_deg": a[rows, best],
        "cost": cost,
    }, exact


def first_pass_settled(road: RoadMap, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                       radius: float = DEFAULT_RADIUS_M, angle_weight_m_per_deg: float = DEFAULT_ANGLE_WEIGHT_M_PER_DEG,
                       k: int = FIRST_PASS_K[0]) -> float:
    """The fraction of poses :func:`match_many` settles in its first pass of ``k`` nearest way-points."""
    yaw = np.asarray(yaw, dtype=float)
    k = max(1, min(k, len(road)))
    _, exact = _match_k(road, np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.cos(yaw), np.sin(yaw),
                        radius, angle_weight_m_per_deg, k)
    return float(exact.mean()) if exact.size else 1.0


def match_many(
    road: RoadMap,
    x: np.ndarray,
    y: np.ndarray,
    yaw: np.ndarray,
    radius: float = DEFAULT_RADIUS_M,
    angle_weight_m_per_deg: float = DEFAULT_ANGLE_WEIGHT_M_PER_DEG,
    k_steps: tuple[int, ...] = FIRST_PASS_K,
) -> dict[str, np.ndarray]:
    """Vectorised :func:`match` for many poses: the same answers, much higher throughput.

    Each pose first competes among its k nearest way-points within the radius (k from
    ``k_steps``, growing); that is exact when the best D is no more than the k-th distance,
    since no farther way-point can have a smaller D (D ≥ E). Poses still unresolved after the
    last step are matched with every way-point in the radius. Returns arrays: ``index`` (-1:
    nothing within the radius), ``reversed``, ``distance_m``, ``angle_deg``, ``cost``,
    ``way_id``, ``lateral_m`` (NaN where nothing matched).
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    yaw = np.asarray(yaw, dtype=float).ravel()
    for name, v in (("x", x), ("y", y), ("yaw", yaw)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"match_many: {name} must be finite everywhere")
    if not (len(x) == len(y) == len(yaw)):
        raise ValueError("match_many: x, y and yaw must have the same length")
    check_pose_args(0.0, 0.0, 0.0, radius)
    c, s = np.cos(yaw), np.sin(yaw)
    n = len(x)
    out = {
        "index": np.full(n, -1, dtype=np.int64),
        "reversed": np.zeros(n, dtype=bool),
        "distance_m": np.full(n, np.nan),
        "angle_deg": np.full(n, np.nan),
        "cost": np.full(n, np.nan),
    }
    todo = np.arange(n)
    for k in k_steps:
        if todo.size == 0:
            break
        k = max(1, min(k, len(road)))
        res, exact = _match_k(road, x[todo], y[todo], c[todo], s[todo], radius, angle_weight_m_per_deg, k)
        done = todo[exact]
        for key in out:
            out[key][done] = res[key][exact]
        todo = todo[~exact]
    for i in todo:  # the rare pose with more than max(k_steps) way-points nearer than its best D
        m = match(road, float(x[i]), float(y[i]), float(yaw[i]), radius, angle_weight_m_per_deg)
        assert m is not None  # a pose with way-points nearer than its best D has a match
        out["index"][i], out["reversed"][i] = m.index, m.reversed
        out["distance_m"][i], out["angle_deg"][i], out["cost"][i] = m.distance_m, m.angle_deg, m.cost
    found = out["index"] >= 0
    idx = np.where(found, out["index"], 0)
    sign = np.where(out["reversed"], -1.0, 1.0)
    lat = sign * (-road.yaw_sin[idx] * (x - road.xy_m[idx, 0]) + road.yaw_cos[idx] * (y - road.xy_m[idx, 1]))
    out["way_id"] = np.where(found, road.way_ids[road.way_index[idx]], -1)
    out["lateral_m"] = np.where(found, np.abs(lat), np.nan)
    for key in ("distance_m", "angle_deg", "cost"):
        out[key] = np.where(found, out[key], np.nan)
    return out


# ----------------------------------------------------------------------------- map pose
def _rot_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_zyx(rotation: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in radians of a rotation matrix, R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r = np.asarray(rotation, dtype=float)
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    roll = math.atan2(r[2, 1], r[2, 2])
    yaw = math.atan2(r[1, 0], r[0, 0])
    return yaw, pitch, roll


def _as_matrix(pose) -> tuple[np.ndarray, bool]:
    """A 4×4 matrix from a gtsam.Pose3 or a 4×4 array; flag says which it was."""
    if hasattr(pose, "matrix") and callable(pose.matrix):
        return np.asarray(pose.matrix(), dtype=float), True
    m = np.asarray(pose, dtype=float)
    if m.shape != (4, 4):
        raise ValueError(f"map_pose: pose must be a gtsam.Pose3 or a 4×4 array, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("map_pose: pose must be finite")
    return m, False


def map_pose(m: Match, pose):
    """The paper's map pose R_t and lateral distance L for a vehicle pose P_t.

    R_t takes x, y and yaw from the map (the matched way-point and road heading) and z, roll and
    pitch from the pose; L = |y of R_t⁻¹ P_t|. ``pose`` is a ``gtsam.Pose3`` or a 4×4 array;
    R_t is returned as the same type. Returns ``(R_t, L)``.
    """
    p, is_gtsam = _as_matrix(pose)
    _, pitch, roll = euler_zyx(p[:3, :3])
    r = np.eye(4)
    r[:3, :3] = _rot_zyx(m.yaw_rad, pitch, roll)
    r[:3, 3] = (m.x_m, m.y_m, p[2, 3])
    tf_translation = r[:3, :3].T @ (p[:3, 3] - r[:3, 3])
    lateral = abs(float(tf_translation[1]))
    if is_gtsam:
        import gtsam

        return gtsam.Pose3(r), lateral
    return r, lateral
