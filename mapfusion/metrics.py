"""Metrics (DESIGN "Metrics", contract).

ATE: both trajectories' positions projected onto the x/y plane, the estimate aligned to the truth
by a rigid SE(3) Umeyama fit (no scale; on planar points a rotation about z and a translation),
and the RMSE of the position differences. The contract asks for equality with evo's APE
(translation, ``--align``) on the 2D-projected pair to 1e-6 m, which fixes the order: project,
then align. (The paper aligns in 6DoF and then projects; on flat trajectories the two agree.)

Online error: the causal estimate against the truth at the same time, no alignment, split into
the parts across and along the true heading. Match rate: frames outside junctions whose matched
OSM way is the way the truth drives on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError


class MetricsError(InputError):
    """Trajectories that cannot be compared (too few common poses, NaN, mismatched shapes)."""


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares R, t (and s) with dst ≈ s·R·src + t (Umeyama 1991). src, dst: (N, d)."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or len(src) < 2:
        raise MetricsError(
            f"umeyama: need two (N, d) arrays of equal shape with N ≥ 2, got {src.shape} and {dst.shape}"
        )
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    s_fix = np.eye(src.shape[1])
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[-1, -1] = -1.0
    r = u @ s_fix @ vt
    scale = 1.0
    if with_scale:
        var = np.mean(np.sum(a * a, axis=1))
        scale = float(np.trace(np.diag(d) @ s_fix) / var) if var > 0 else 1.0
    t = mu_d - scale * r @ mu_s
    return r, t, scale


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt_s: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of poses whose timestamps match within ``max_dt_s`` (nearest neighbour)."""
    t_a = np.asarray(t_a, dtype=float)
    t_b = np.asarray(t_b, dtype=float)
    j = np.clip(np.searchsorted(t_b, t_a), 1, len(t_b) - 1)
    left = np.abs(t_b[j - 1] - t_a) <= np.abs(t_b[j] - t_a)
    j = np.where(left, j - 1, j)
    ok = np.abs(t_b[j] - t_a) <= max_dt_s
    return np.flatnonzero(ok), j[ok]


def _check_pair(gt: np.ndarray, est: np.ndarray, what: str, min_n: int = 3) -> None:
    if gt.shape != est.shape or gt.ndim != 2 or gt.shape[1] not in (2, 3):
        raise MetricsError(f"{what}: need two (N, 2) or (N, 3) arrays of equal shape, got {gt.shape} and {est.shape}")
    if len(gt) < min_n:
        raise MetricsError(f"{what}: need at least {min_n} common poses, got {len(gt)}")
    if not (np.all(np.isfinite(gt)) and np.all(np.isfinite(est))):
        raise MetricsError(f"{what}: NaN or infinite positions")


def _planar(p: np.ndarray) -> np.ndarray:
    out = np.zeros((len(p), 3))
    out[:, :2] = p[:, :2]
    return out


def aligned_xy(truth_xyz: np.ndarray, estimate_xyz: np.ndarray) -> np.ndarray:
    """The estimate's x/y after the ATE's alignment (projected, then rigid SE(3) Umeyama)."""
    gt, est = _planar(np.asarray(truth_xyz, float)), _planar(np.asarray(estimate_xyz, float))
    r, t, _ = umeyama(est, gt)
    return (est @ r.T + t)[:, :2]


def ate(truth_xyz: np.ndarray, estimate_xyz: np.ndarray) -> float:
    """Absolute trajectory error (m) of associated position pairs (see the module docstring)."""
    gt = np.asarray(truth_xyz, dtype=float)
    est = np.asarray(estimate_xyz, dtype=float)
    _check_pair(gt, est, "ate")
    d = aligned_xy(gt, est) - gt[:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def delocalized(ate_m: float, threshold_m: float = 20.0) -> bool:
    """De-localised: ATE above the threshold (paper IV.B: 20 m, the widest road observed)."""
    return bool(ate_m > threshold_m)


@dataclass(frozen=True)
class OnlineError:
    """The causal estimate against the truth at the same time, without alignment (metres)."""

    rmse_m: float
    max_m: float
    lateral_rmse_m: float
    longitudinal_rmse_m: float
    frames: int
    end_m: float | None = None  # median error over the last END_WINDOW_S (None: no times given)


#: The window at a drive's end over which ``OnlineError.end_m`` is the median error: where the estimate ends up
#: (found again, or still lost), which the ATE's alignment over the whole drive does not say.
END_WINDOW_S = 60.0


def online_error(truth_xy: np.ndarray, truth_yaw_rad: np.ndarray, estimate_xy: np.ndarray,
                 t_s: np.ndarray | None = None) -> OnlineError:
    """RMSE and max of the position error, and its parts across and along the true heading; with the frames'
    times ``t_s`` (s, non-decreasing) also the median error over the last ``END_WINDOW_S`` of them."""
    gt = np.asarray(truth_xy, float)[:, :2]
    est = np.asarray(estimate_xy, float)[:, :2]
    _check_pair(gt, est, "online error", min_n=1)
    if t_s is not None and np.shape(t_s) != (len(gt),):
        raise MetricsError(f"online error: {np.shape(t_s)} times for {len(gt)} poses")
    d = est - gt
    c, s = np.cos(truth_yaw_rad), np.sin(truth_yaw_rad)
    lon = c * d[:, 0] + s * d[:, 1]
    lat = -s * d[:, 0] + c * d[:, 1]
    e = np.hypot(d[:, 0], d[:, 1])
    rms = lambda v: float(np.sqrt(np.mean(v * v)))  # noqa: E731
    end = None
    if t_s is not None:
        t = np.asarray(t_s, float)
        end = float(np.median(e[t >= t[-1] - END_WINDOW_S]))
    return OnlineError(rms(e), float(e.max()), rms(lat), rms(lon), len(e), end)


def relocalisation_m(driven_m: np.ndarray, error_m: np.ndarray, from_m: float, within_m: float = 10.0,
                     hold_m: float = 100.0) -> float | None:
    """Distance driven from ``from_m`` (a kidnap) until the online error stays under ``within_m`` for the next
    ``hold_m`` of driving (issue 17's ``relocalisation_m``), or None when it never does. ``driven_m``
    (non-decreasing) and ``error_m`` are per frame; a stretch that reaches the drive's end counts only when it
    is ``hold_m`` long."""
    d, e = np.asarray(driven_m, float), np.asarray(error_m, float)
    if d.shape != e.shape:
        raise InputError(f"relocalisation_m: {d.shape} distances but {e.shape} errors")
    sel = d >= from_m
    d, e = d[sel], e[sel]
    bad = ~(e < within_m)
    idx = np.append(np.flatnonzero(bad), len(d))  # the bad frames, then the end
    nxt = idx[np.searchsorted(idx, np.arange(len(d)))]  # each frame's next bad frame (or len(d))
    for i in np.flatnonzero(~bad):
        j = nxt[i]
        end_m = d[j] if j < len(d) else d[-1]
        if end_m - d[i] >= hold_m:
            return float(d[i] - from_m)
    return None


def zone_rmse(truth_xy: np.ndarray, estimate_xy: np.ndarray, mask: np.ndarray) -> float | None:
    """Online RMSE over the frames in ``mask`` (e.g. GPS-denied zones); None when there are none."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return None
    d = np.asarray(estimate_xy, float)[mask, :2] - np.asarray(truth_xy, float)[mask, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def match_rate(true_way: np.ndarray, matched_way: np.ndarray, continuations: dict | None = None) -> float | None:
    """Fraction of frames outside junctions (``true_way`` ≥ 0) matched to the way the truth is on.

    With ``continuations`` (way → ways continuing it through a vertex of degree 2, see
    :meth:`RoadMap.continuations`), a match on a way that merely continues the true one counts
    too: OSM splits a road into ways anywhere, and a split that is no junction is the same road.
    """
    true_way = np.asarray(true_way)
    matched = np.asarray(matched_way)
    sel = true_way >= 0
    if not sel.any():
        return None
    ok = matched[sel] == true_way[sel]
    if continuations:
        ok |= np.array([int(m) in continuations.get(int(t), ()) for t, m in zip(true_way[sel], matched[sel])])
    return float(np.mean(ok))


def rpe_per_100m(
    truth_xy: np.ndarray,
    truth_yaw_rad: np.ndarray,
    estimate_xy: np.ndarray,
    estimate_yaw_rad: np.ndarray,
    segment_m: float = 100.0,
) -> float | None:
    """Relative position error over ``segment_m`` of driving (m): for every frame i and the frame j
    ``segment_m`` further along the true path, the difference between the true and the estimated
    displacement i → j, each expressed in its own frame at i; the RMS over all i (evo's RPE,
    translation part, with a distance delta). None on a drive shorter than one segment."""
    gt = np.asarray(truth_xy, float)[:, :2]
    est = np.asarray(estimate_xy, float)[:, :2]
    _check_pair(gt, est, "rpe", min_n=2)
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(gt, axis=0).T))))
    if s[-1] < segment_m:
        return None
    i = np.arange(len(s))
    j = np.searchsorted(s, s + segment_m)
    ok = j < len(s)
    i, j = i[ok], j[ok]

    def local(p, yaw):
        d = p[j] - p[i]
        c, sn = np.cos(yaw[i]), np.sin(yaw[i])
        return np.column_stack([c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]])

    e = local(est, np.asarray(estimate_yaw_rad, float)) - local(gt, np.asarray(truth_yaw_rad, float))
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


#: KITTI's odometry benchmark: segment lengths (m) and the frame step between segment starts.
KITTI_SEGMENTS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP_FRAMES = 10


@dataclass(frozen=True)
class KittiError:
    """KITTI's odometry metric: mean translational error (%) and rotational error (deg per 100 m)
    over every segment of 100–800 m starting at every 10th frame; None where the drive has none."""

    t_err_percent: float | None
    r_err_deg_per_100m: float | None
    segments: int


def kitti_errors(truth_poses: np.ndarray, estimate_poses: np.ndarray, scale: float = 1.0) -> KittiError:
    """KITTI's t_err and r_err (as its development kit computes them) of time-associated (N, 4, 4)
    poses: for a segment from frame i to the first frame j more than L metres further along the
    true path, the error of the estimated motion i → j against the true one, its translation over
    L and its rotation angle over L, averaged over all segments. ``scale`` multiplies the
    estimate's translations first (KITTI's monocular results are scored after one fitted scale)."""
    gt = np.asarray(truth_poses, dtype=float)
    est = np.array(estimate_poses, dtype=float)
    _check_pair(gt[:, :3, 3], est[:, :3, 3], "kitti", min_n=2)
    est[:, :3, 3] *= scale
    dist = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))))
    inv_gt, inv_est = np.linalg.inv(gt), np.linalg.inv(est)
    starts = np.arange(0, len(gt), KITTI_STEP_FRAMES)
    t_errs, r_errs = [], []
    for seg in KITTI_SEGMENTS_M:  # the development kit's loop, a segment length at a time over all starts
        ends = np.searchsorted(dist, dist[starts] + seg, side="right")
        ok = ends < len(gt)
        i, j = starts[ok], ends[ok]
        err = np.linalg.inv(inv_est[i] @ est[j]) @ (inv_gt[i] @ gt[j])
        cos = np.clip(0.5 * (np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0), -1.0, 1.0)
        t_errs.append(np.linalg.norm(err[:, :3, 3], axis=1) / seg)
        r_errs.append(np.arccos(cos) / seg)
    t_all, r_all = np.concatenate(t_errs), np.concatenate(r_errs)
    if not len(t_all):
        return KittiError(None, None, 0)
    return KittiError(100.0 * float(t_all.mean()), 100.0 * float(np.degrees(r_all.mean())), len(t_all))


def global_scale(truth_xyz: np.ndarray, estimate_xyz: np.ndarray) -> float:
    """The one scale that best maps the estimate's positions onto the truth's (Umeyama with scale)."""
    _, _, s = umeyama(np.asarray(estimate_xyz, float), np.asarray(truth_xyz, float), with_scale=True)
    return float(s)


@dataclass(frozen=True)
class OdometryStats:
    """What an odometry's error is made of, against the truth of the same drive (issue 22: the
    statistics a simulated odometry is fitted on). Lengths in metres along the true path."""

    driven_m: float
    global_scale: float  # the one scale that maps the odometry onto the truth best
    kitti_t_err_percent: float | None  # after that scale
    kitti_r_err_deg_per_100m: float | None
    yaw_drift_deg_per_100m: float  # slope of the heading error over the distance driven
    scale_window_sigma: float  # σ of the scale fitted per 100 m window, relative to the global one
    scale_rw_per_sqrt_m: float  # σ of the change between consecutive windows / √100 m
    start_scale_bias: float | None  # the scale over the first 30 s relative to the global one, minus 1
    lateral_rmse_m: float  # across the true heading, after a similarity fit of the whole drive
    lateral_power_short: float  # share of the lateral error's variance at wavelengths under 50 m
    lateral_power_long: float  # ... and over 500 m
    jumps_per_km: float  # steps off by more than 10 robust σ of the step errors (and JUMP_MIN_M)
    step_error_autocorrelation: tuple[float, float, float]  # of the step-length errors at lags 1, 10, 100


#: A step error counts as a jump only beyond this too: a re-initialisation moves metres, not millimetres.
JUMP_MIN_M = 1.0


def odometry_stats(t_s: np.ndarray, truth_poses: np.ndarray, odometry_poses: np.ndarray) -> OdometryStats:
    """The statistics of :class:`OdometryStats` for time-associated (N, 4, 4) poses."""
    gt = np.asarray(truth_poses, dtype=float)
    od = np.asarray(odometry_poses, dtype=float)
    _check_pair(gt[:, :3, 3], od[:, :3, 3], "odometry stats", min_n=20)
    gxy, oxy = gt[:, :2, 3], od[:, :2, 3]
    g_step = np.linalg.norm(np.diff(gxy, axis=0), axis=1)
    o_step = np.linalg.norm(np.diff(oxy, axis=0), axis=1)
    dist = np.concatenate(([0.0], np.cumsum(g_step)))
    scale = global_scale(gt[:, :3, 3], od[:, :3, 3])
    k = kitti_errors(gt, od, scale)
    # heading error over distance
    yaw_g = np.unwrap(np.arctan2(gt[:, 1, 0], gt[:, 0, 0]))
    yaw_o = np.unwrap(np.arctan2(od[:, 1, 0], od[:, 0, 0]))
    dyaw = (yaw_o - yaw_o[0]) - (yaw_g - yaw_g[0])
    drift = float(np.polyfit(dist, np.degrees(dyaw), 1)[0] * 100.0) if dist[-1] > 0 else 0.0
    # scale per 100 m window
    edges = np.searchsorted(dist, np.arange(0.0, dist[-1], 100.0))
    ratios = []
    for a, b in zip(edges[:-1], edges[1:]):
        g = g_step[a:b].sum()
        if g > 50.0:
            ratios.append(scale * o_step[a:b].sum() / g)
    r = np.asarray(ratios)
    window_sigma = float(r.std()) if len(r) > 1 else 0.0
    rw = float(np.std(np.diff(r)) / np.sqrt(2.0) / 10.0) if len(r) > 2 else 0.0
    first = np.searchsorted(t_s, t_s[0] + 30.0)
    start_g = g_step[:first].sum()
    start_bias = float(scale * o_step[:first].sum() / start_g - 1.0) if start_g > 20.0 else None
    # lateral error after a similarity fit of the whole drive, resampled every metre
    rot, tr, s = umeyama(oxy, gxy, with_scale=True)
    aligned = s * oxy @ rot.T + tr
    heading = np.column_stack([np.cos(yaw_g), np.sin(yaw_g)])
    e = aligned - gxy
    lateral = heading[:, 0] * e[:, 1] - heading[:, 1] * e[:, 0]
    grid = np.arange(0.0, dist[-1], 1.0)
    lat_1m = np.interp(grid, dist, lateral) if len(grid) > 8 else lateral
    spec = np.abs(np.fft.rfft(lat_1m - lat_1m.mean())) ** 2
    freq = np.fft.rfftfreq(len(lat_1m), d=1.0)
    total = spec[1:].sum() or 1.0
    short = float(spec[1:][freq[1:] > 1 / 50.0].sum() / total)
    long = float(spec[1:][freq[1:] < 1 / 500.0].sum() / total)
    # jumps and the step errors' memory
    step_err = scale * o_step - g_step
    robust_sigma = float(np.median(np.abs(step_err - np.median(step_err)))) * 1.4826
    jumps = int(np.sum(np.abs(step_err - np.median(step_err)) > max(10.0 * robust_sigma, JUMP_MIN_M)))

    def acf(lag: int) -> float:
        x = step_err - step_err.mean()
        if len(x) <= lag or not np.any(x):
            return 0.0
        return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))

    return OdometryStats(float(dist[-1]), scale, k.t_err_percent, k.r_err_deg_per_100m, drift, window_sigma, rw,
                         start_bias, float(np.sqrt(np.mean(lateral**2))), short, long,
                         jumps / max(dist[-1] / 1000.0, 1e-9), (acf(1), acf(10), acf(100)))
