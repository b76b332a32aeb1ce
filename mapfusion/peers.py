"""Reference peers: methods the test bed scores beside Map-Fusion (``[[estimators]]``, entry points ``ekf`` and
``mapmatch`` of the group ``mapfusion.estimators``), so that a table says what the map adds over the classical way.

:class:`GpsOdometryEkf` is the filter localisation papers compare with: an extended Kalman filter on the plane
(position, heading, the odometry's log-scale) that dead-reckons with the odometry's relative motion and corrects
with GPS fixes behind a χ² gate (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, ch. 3 and 7; the
loosely coupled GNSS/odometry filter of Groves, *Principles of GNSS, Inertial, and Multisensor Integrated
Navigation Systems*, 2nd ed., 2013, ch. 14 and 16). Wheel speed, where fed, is a measurement of the step's
length, so it calibrates the odometry's scale (Groves ch. 16.2), and with the gyro it replaces a step the odometry
got wrong. It never reads the map.

:class:`OfflineMapMatching` map-matches the EKF's whole track onto the road graph after the drive, as FMM
(Yang & Gidófalvi 2018) and Valhalla's Meili do with the HMM of Newson & Krumm (2009): candidates are the roads
within ``radius_m`` of points every ``step_m`` of the track, emissions a Gaussian in the distance (σ
``sigma_m``), transitions an exponential in the difference between the road-network distance and the track's
(β ``beta_m``); Viterbi picks the most probable road sequence and every frame's estimate is its track position
projected onto that road. It is offline: it sees the whole drive before it answers, which Map-Fusion never
does, so its online error is that of a smoother, not a tracker.

Both are streaming estimators (``mapfusion.harness.estimators.StreamingEstimator``): made as ``Class(road,
**params)``, fed ``add_odometry``, ``add_gps`` and ``add_wheel_speed``.
"""

from __future__ import annotations

import math

import numpy as np

from .roadmap import RoadMap

#: χ² with two degrees of freedom at 99.9%: a fix farther than this (squared Mahalanobis) is an outlier.
GATE_CHI2 = 13.82


#: Fixes a (re)start needs, and the least odometry movement (its own units) over them.
MIN_START_FIXES, MIN_START_ODOMETRY = 3, 1e-3


def _yaw_of(m: np.ndarray) -> float:
    return math.atan2(m[1, 0], m[0, 0])


def _similarity_2d(src: np.ndarray, dst: np.ndarray) -> tuple[float, float, np.ndarray] | None:
    """(turn, scale, shift) minimising Σ |scale · R(turn) · src + shift − dst|² (Umeyama 1991, on the plane);
    None when ``src`` does not move."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    var = float(np.sum(a * a))
    if var < MIN_START_ODOMETRY**2:
        return None
    cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    dot = float(np.sum(a * b))
    turn = math.atan2(cross, dot)
    scale = math.hypot(cross, dot) / var
    c, s = math.cos(turn), math.sin(turn)
    shift = md - scale * np.array([[c, -s], [s, c]]) @ ms
    return turn, scale, shift


class GpsOdometryEkf:
    """GPS + odometry (+ wheel speed and gyro) on the plane, without the map. State: x, y (m, the map's ENU frame),
    yaw (rad) and ln s (true metres per odometry metre). Noise grows with the distance driven: a random walk of
    ``pos_sigma_per_sqrt_m`` (m/√m), ``yaw_sigma_per_sqrt_m`` (rad/√m) and ``scale_sigma_per_sqrt_m`` (1/√m). It
    starts once two fixes lie ``init_baseline_m`` apart (heading and scale from the fixes' displacement against
    the odometry's), and starts again the same way after ``gate_after_rejected`` fixes in a row fell outside its
    χ² gate (dead-reckoning meanwhile); a fix with no σ counts ``gps_sigma_m``. Where wheel speed is fed, it
    measures each step's length (so the scale is calibrated), and a step whose length disagrees with it by more
    than ``veto_m`` and ``veto_fraction``, or whose turn disagrees with the gyro's by more than ``veto_deg`` (a VO
    that jumped, stalled or guessed across a gap), is replaced by wheel + gyro's own dead reckoning over it;
    without a wheel, a step faster than ``max_speed_mps`` is left out. Such a step's heading is uncertain by the
    gyro's bias over it (``gyro_bias_sigma_radps``: the simulated IMU's σ of its bias), so the fixes after a
    tunnel pass the gate and put it right. Without a wheel, a step across an odometry gap longer than ``gap_s``
    (a VO that lost track guesses the motion over it) starts the filter again from the fixes that follow
    (dead-reckoning meanwhile)."""

    def __init__(self, road: RoadMap, pos_sigma_per_sqrt_m: float = 0.05, yaw_sigma_per_sqrt_m: float = 0.005,
                 scale_sigma_per_sqrt_m: float = 0.002, gps_sigma_m: float = 2.0, init_baseline_m: float = 20.0,
                 wheel_sigma_fraction: float = 0.02, gate_after_rejected: int = 3, veto_m: float = 1.0,
                 veto_fraction: float = 0.5, veto_deg: float = 1.0, max_speed_mps: float = 70.0,
                 gyro_bias_sigma_radps: float = 0.005, gap_s: float = 1.0) -> None:
        if min(pos_sigma_per_sqrt_m, yaw_sigma_per_sqrt_m, scale_sigma_per_sqrt_m, gps_sigma_m, init_baseline_m,
               max_speed_mps) <= 0:
            raise ValueError("GpsOdometryEkf: every σ, init_baseline_m and max_speed_mps must be > 0")
        self.projection = road.projection
        self.q_pos, self.q_yaw, self.q_scale = pos_sigma_per_sqrt_m, yaw_sigma_per_sqrt_m, scale_sigma_per_sqrt_m
        self.gps_sigma_m, self.init_baseline_m = gps_sigma_m, init_baseline_m
        self.wheel_fraction, self.gate_after = wheel_sigma_fraction, gate_after_rejected
        self.veto_m, self.veto_fraction, self.max_speed_mps = veto_m, veto_fraction, max_speed_mps
        self.veto_rad = math.radians(veto_deg)
        self.gyro_bias_sigma = gyro_bias_sigma_radps
        self.gap_s = gap_s
        self.odo = np.eye(4)  # the odometry's own pose (its frame)
        self.x: np.ndarray | None = None  # [x, y, yaw, ln s] once started
        self.P = np.zeros((4, 4))
        self._window: list[tuple[np.ndarray, np.ndarray]] = []  # (fix ENU, odometry position) of a (re)start
        self._restarting = True
        self._t: float | None = None  # the last frame's time
        # wheel + gyro dead reckoning since the last frame, in that frame's body axes: distance, x, y, yaw
        self._wheel_m, self._dr_x, self._dr_y, self._gyro_yaw = 0.0, 0.0, 0.0, 0.0
        self._wheel_fed = self._gyro_fed = False
        self._wheel_t: float | None = None
        self._wheel_v = 0.0
        self._gyro_t: float | None = None
        self._gyro_w = 0.0
        self.rejected_in_a_row = 0
        self.fixes_used = self.fixes_rejected = self.restarts = self.steps_vetoed = 0

    # ------------------------------------------------------------------ inputs
    def add_wheel_speed(self, t_s: float, speed_mps: float) -> None:
        if self._wheel_t is not None and t_s > self._wheel_t:
            d = self._wheel_v * (t_s - self._wheel_t)
            self._wheel_m += abs(d)
            self._dr_x += d * math.cos(self._gyro_yaw)
            self._dr_y += d * math.sin(self._gyro_yaw)
        self._wheel_t, self._wheel_v, self._wheel_fed = t_s, speed_mps, True

    def add_imu(self, t_s: float, accel_mps2, gyro_radps) -> None:
        if self._gyro_t is not None and t_s > self._gyro_t:
            self._gyro_yaw += self._gyro_w * (t_s - self._gyro_t)
        self._gyro_t, self._gyro_w, self._gyro_fed = t_s, float(gyro_radps[2]), True

    def add_odometry(self, t_s: float, relative_pose: np.ndarray) -> None:
        rel = np.asarray(relative_pose, dtype=float)
        self.odo = self.odo @ rel
        dt = t_s - self._t if self._t is not None else 0.0
        self._t = t_s
        wheel_m, dr_x, dr_y, gyro_yaw = self._wheel_m, self._dr_x, self._dr_y, self._gyro_yaw
        self._wheel_m = self._dr_x = self._dr_y = self._gyro_yaw = 0.0
        if self.x is None:
            return
        dx, dy, dyaw = rel[0, 3], rel[1, 3], _yaw_of(rel)
        s = math.exp(self.x[3])
        odo_m = math.hypot(dx, dy)
        measured, extra = False, None
        if self._wheel_fed:
            turned = self._gyro_fed and abs(math.remainder(dyaw - gyro_yaw, 2 * math.pi)) > self.veto_rad
            if turned or abs(s * odo_m - wheel_m) > max(self.veto_m, self.veto_fraction * wheel_m):
                self.steps_vetoed += 1  # wheel + gyro's own dead reckoning over the step
                dx, dy = dr_x / s, dr_y / s
                dyaw = gyro_yaw if self._gyro_fed else 0.0
                # an unknown gyro bias over the step turns its heading, and its end, by as much
                yaw_sigma = self.gyro_bias_sigma * dt if self._gyro_fed else math.pi / 4
                extra = (yaw_sigma, 0.5 * yaw_sigma * wheel_m + self.wheel_fraction * wheel_m)
            else:
                measured = wheel_m > 0.0 and odo_m > 0.05
        elif dt > 0 and s * odo_m / dt > self.max_speed_mps:
            self.steps_vetoed += 1  # an impossible speed: a jump, left out
            dx = dy = dyaw = 0.0
        elif dt > self.gap_s and not self._restarting:
            # the odometry lost track and guessed its motion across the gap: start again from the next fixes
            self.restarts += 1
            self._restarting = True
            self._window = []
        self._predict(dx, dy, dyaw)
        if extra is not None:
            self.P += np.diag([extra[1] ** 2, extra[1] ** 2, extra[0] ** 2, 0.0])
        if measured:  # the wheel's distance measures the step: s × odometry step
            s = math.exp(self.x[3])
            h = np.array([[0.0, 0.0, 0.0, s * odo_m]])
            r = (self.wheel_fraction * wheel_m + 0.02) ** 2
            self._update(np.array([wheel_m - s * odo_m]), h, np.array([[r]]), gate=False)

    def add_gps(self, t_s: float, lat: float, lon: float, alt: float | None = None,
                sigma_m: float | None = None) -> None:
        ex, ey = self.projection.to_enu(lat, lon)
        z = np.array([float(ex), float(ey)])
        sigma = sigma_m if sigma_m is not None and sigma_m > 0 else self.gps_sigma_m
        if self._restarting:
            self._start(z, sigma)
            return
        assert self.x is not None
        h = np.zeros((2, 4))
        h[0, 0] = h[1, 1] = 1.0
        if self._update(z - self.x[:2], h, np.eye(2) * sigma**2, gate=True):
            self.fixes_used += 1
            self.rejected_in_a_row = 0
            return
        self.fixes_rejected += 1
        self.rejected_in_a_row += 1
        if self.rejected_in_a_row >= self.gate_after:  # lost: start again from the fixes, dead-reckoning meanwhile
            self.restarts += 1
            self.rejected_in_a_row = 0
            self._restarting = True
            self._window = []
            self._start(z, sigma)

    def estimate(self) -> np.ndarray | None:
        if self.x is None:
            return None
        x, y, yaw, _ = self.x
        m = np.eye(4)
        m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        m[:2, 3] = (x, y)
        return m

    @property
    def scale(self) -> float:
        """True metres per odometry metre (nan before the start)."""
        return math.exp(self.x[3]) if self.x is not None else math.nan

    # ------------------------------------------------------------------ internals
    def _predict(self, dx: float, dy: float, dyaw: float) -> None:
        assert self.x is not None
        x, y, yaw, ls = self.x
        s = math.exp(ls)
        c, sn = math.cos(yaw), math.sin(yaw)
        ex, ey = c * dx - sn * dy, sn * dx + c * dy  # the step in ENU, at the odometry's scale
        self.x = np.array([x + s * ex, y + s * ey, math.remainder(yaw + dyaw, 2 * math.pi), ls])
        f = np.eye(4)
        f[0, 2], f[1, 2] = -s * ey, s * ex
        f[0, 3], f[1, 3] = s * ex, s * ey
        dist = s * math.hypot(dx, dy)
        q = np.diag([self.q_pos**2 * dist, self.q_pos**2 * dist, self.q_yaw**2 * dist, self.q_scale**2 * dist])
        self.P = f @ self.P @ f.T + q

    def _start(self, z: np.ndarray, sigma: float) -> None:
        """A (re)start from the window's fixes: the similarity (turn, scale, shift) that puts the odometry's
        positions on them, fitted once they span ``init_baseline_m`` (least squares, fixes off by more than three σ
        and 5 m left out and the fit repeated), over at least ``MIN_START_FIXES`` fixes."""
        self._window.append((z, self.odo[:2, 3].copy()))
        if len(self._window) < MIN_START_FIXES:
            return
        fixes = np.array([w[0] for w in self._window])
        odo = np.array([w[1] for w in self._window])
        if np.max(np.hypot(*(fixes - fixes[0]).T)) < self.init_baseline_m:
            return
        keep = np.ones(len(fixes), dtype=bool)
        for _ in range(2):
            fit = _similarity_2d(odo[keep], fixes[keep])
            if fit is None:
                return
            turn, scale, shift = fit
            c, sn = math.cos(turn), math.sin(turn)
            pred = scale * odo @ np.array([[c, -sn], [sn, c]]).T + shift
            res = np.hypot(*(pred - fixes).T)
            keep = res <= max(3.0 * sigma, 5.0)
            if keep.sum() < MIN_START_FIXES:
                return
        span = float(np.max(np.hypot(*(fixes[keep] - fixes[keep][0]).T)))
        if span < self.init_baseline_m:
            return
        here = scale * np.array([[c, -sn], [sn, c]]) @ self.odo[:2, 3] + shift
        yaw = math.remainder(_yaw_of(self.odo) + turn, 2 * math.pi)
        self.x = np.array([here[0], here[1], yaw, math.log(scale)])
        rel_sigma = math.sqrt(2.0) * sigma / span  # a baseline's direction and length from fixes of σ
        self.P = np.diag([sigma**2, sigma**2, rel_sigma**2, rel_sigma**2])
        self._window.clear()
        self._restarting = False

    def _update(self, innovation: np.ndarray, h: np.ndarray, r: np.ndarray, gate: bool) -> bool:
        s = h @ self.P @ h.T + r
        if gate and float(innovation @ np.linalg.solve(s, innovation)) > GATE_CHI2:
            return False
        k = self.P @ h.T @ np.linalg.inv(s)
        assert self.x is not None
        self.x = self.x + k @ innovation
        self.x[2] = math.remainder(self.x[2], 2 * math.pi)
        i_kh = np.eye(4) - k @ h
        self.P = i_kh @ self.P @ i_kh.T + k @ r @ k.T  # Joseph form: stays symmetric positive definite
        return True


class OfflineMapMatching:
    """The EKF's track (:class:`GpsOdometryEkf`, fed the same inputs; ``ekf`` its parameters) map-matched onto the
    road graph after the drive by an HMM (see the module docstring). Its answer is :meth:`final_estimates`; it
    gives no causal estimate (``estimate()`` is always None)."""

    def __init__(self, road: RoadMap, radius_m: float = 30.0, step_m: float = 5.0, sigma_m: float = 5.0,
                 beta_m: float = 5.0, max_candidates: int = 8, ekf: dict | None = None) -> None:
        if min(radius_m, step_m, sigma_m, beta_m) <= 0 or max_candidates < 1:
            raise ValueError("OfflineMapMatching: radius_m, step_m, sigma_m and beta_m must be > 0, "
                             "max_candidates ≥ 1")
        from scipy.sparse import coo_matrix

        self.road, self.radius_m, self.step_m = road, radius_m, step_m
        self.sigma_m, self.beta_m, self.k = sigma_m, beta_m, max_candidates
        self.ekf = GpsOdometryEkf(road, **(ekf or {}))
        self._t: list[float] = []
        self._pose: list[np.ndarray] = []
        n = len(road.vertex_xy_m)
        shortest: dict[tuple[int, int], float] = {}  # the shortest of parallel edges between two vertices
        for a, b, length in zip(road.edge_u.tolist(), road.edge_v.tolist(), road.edge_length_m.tolist()):
            if a != b:
                key = (min(a, b), max(a, b))
                shortest[key] = min(shortest.get(key, math.inf), float(length))
        ends = np.array(list(shortest), dtype=np.int64).reshape(-1, 2)
        lengths = np.array(list(shortest.values()), dtype=float)
        self.graph = coo_matrix((np.concatenate([lengths, lengths]),
                                 (np.concatenate([ends[:, 0], ends[:, 1]]), np.concatenate([ends[:, 1], ends[:, 0]]))),
                                shape=(n, n)).tocsr()

    def add_odometry(self, t_s: float, relative_pose: np.ndarray) -> None:
        self.ekf.add_odometry(t_s, relative_pose)
        p = self.ekf.estimate()
        if p is not None:
            self._t.append(t_s)
            self._pose.append(p)

    def add_gps(self, t_s: float, lat: float, lon: float, alt: float | None = None,
                sigma_m: float | None = None) -> None:
        self.ekf.add_gps(t_s, lat, lon, alt, sigma_m)

    def add_wheel_speed(self, t_s: float, speed_mps: float) -> None:
        self.ekf.add_wheel_speed(t_s, speed_mps)

    def add_imu(self, t_s: float, accel_mps2, gyro_radps) -> None:
        self.ekf.add_imu(t_s, accel_mps2, gyro_radps)

    def estimate(self) -> None:
        return None

    # ------------------------------------------------------------------ the match
    def _candidates(self, xy: np.ndarray) -> list[tuple[int, int, float]]:
        """(edge, way-point, distance) of the nearest way-point of each edge within the radius, nearest first."""
        road = self.road
        near = road.query_radius(float(xy[0]), float(xy[1]), self.radius_m)
        near = near[road.edge[near] >= 0]
        if near.size == 0:
            return []
        d = np.hypot(road.xy_m[near, 0] - xy[0], road.xy_m[near, 1] - xy[1])
        best: dict[int, tuple[int, float]] = {}
        for i, dist in zip(near.tolist(), d.tolist()):
            e = int(road.edge[i])
            if e not in best or dist < best[e][1]:
                best[e] = (i, dist)
        out = sorted(((e, i, dist) for e, (i, dist) in best.items()), key=lambda c: (c[2], c[0]))
        return out[: self.k]

    def _network_m(self, a: tuple[int, int, float], b: tuple[int, int, float], from_vertex: dict[int, np.ndarray]
                   ) -> float:
        road = self.road
        ea, ia, _ = a
        eb, ib, _ = b
        sa, sb = float(road.s_m[ia]), float(road.s_m[ib])
        if ea == eb:
            return abs(sb - sa)
        la, lb = float(road.edge_length_m[ea]), float(road.edge_length_m[eb])
        best = math.inf
        for va, da in ((int(road.edge_u[ea]), sa), (int(road.edge_v[ea]), la - sa)):
            row = from_vertex[va]
            for vb, db in ((int(road.edge_u[eb]), sb), (int(road.edge_v[eb]), lb - sb)):
                best = min(best, da + float(row[vb]) + db)
        return best

    def final_estimates(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """Every frame the EKF estimated, its position on the road the match chose (the EKF's own where no road
        lies within the radius): (t_s, 4 × 4 poses)."""
        if not self._pose:
            return np.empty(0), []
        xy = np.array([p[:2, 3] for p in self._pose])
        along = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
        samples = [0]
        for k in range(1, len(xy)):
            if along[k] - along[samples[-1]] >= self.step_m:
                samples.append(k)
        chosen = self._viterbi([self._candidates(xy[k]) for k in samples], along[samples])
        sample_of = np.searchsorted(np.asarray(samples), np.arange(len(xy)), side="right") - 1
        out = []
        for k, p in enumerate(self._pose):
            on = chosen[int(sample_of[k])]
            out.append(p if on is None else self._on_road(on[0], xy[k], _yaw_of(p)))
        return np.asarray(self._t), out

    def _viterbi(self, cands: list[list[tuple[int, int, float]]], along_m: np.ndarray
                 ) -> list[tuple[int, int, float] | None]:
        """The most probable candidate of each sample, one Viterbi pass over each stretch of samples that all
        have candidates (None for a sample without)."""
        from scipy.sparse.csgraph import dijkstra

        limit = 4.0 * self.step_m + 2.0 * self.radius_m + 100.0
        chosen: list[tuple[int, int, float] | None] = [None] * len(cands)
        i = 0
        while i < len(cands):
            if not cands[i]:
                i += 1
                continue
            j = i
            while j + 1 < len(cands) and cands[j + 1]:
                j += 1
            score = [-0.5 * (c[2] / self.sigma_m) ** 2 for c in cands[i]]
            back: list[list[int]] = []
            for n in range(i + 1, j + 1):
                prev, cur = cands[n - 1], cands[n]
                verts = sorted({int(v) for e, _, _ in prev for v in (self.road.edge_u[e], self.road.edge_v[e])})
                dist = dijkstra(self.graph, directed=False, indices=verts, limit=limit)
                from_vertex = {v: dist[r] for r, v in enumerate(verts)}
                moved = float(along_m[n] - along_m[n - 1])
                new_score, pointers = [], []
                for c in cur:
                    emit = -0.5 * (c[2] / self.sigma_m) ** 2
                    trans = [score[a] - abs(self._network_m(p, c, from_vertex) - moved) / self.beta_m
                             for a, p in enumerate(prev)]
                    a = int(np.argmax(trans))
                    new_score.append(trans[a] + emit if math.isfinite(trans[a]) else -1e9 + emit)
                    pointers.append(a)
                score = new_score
                back.append(pointers)
            a = int(np.argmax(score))
            for n in range(j, i - 1, -1):
                chosen[n] = cands[n][a]
                if n > i:
                    a = back[n - i - 1][a]
            i = j + 1
        return chosen

    def _on_road(self, edge: int, xy: np.ndarray, yaw_est: float) -> np.ndarray:
        """The pose at the edge's way-point nearest ``xy``, heading along the road the way the estimate heads."""
        idx = np.arange(self.road.edge_start[edge], self.road.edge_end[edge])
        w = idx[int(np.argmin(np.hypot(*(self.road.xy_m[idx] - xy).T)))]
        yaw = float(self.road.yaw_rad[w])
        if math.cos(yaw - yaw_est) < 0:  # the road's direction the vehicle drives
            yaw += math.pi
        m = np.eye(4)
        m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        m[:2, 3] = self.road.xy_m[w]
        return m
