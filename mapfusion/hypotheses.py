"""Which road the vehicle is on, as a hidden state over time (DESIGN item 8): an online hidden
Markov model over the road graph's edges and travel directions.

At every step the candidates are the (edge, direction) pairs with a way-point within the search
radius of the predicted pose (a one-way edge in its legal direction only). A candidate's emission is
the paper's matching cost taken as a negative log-likelihood, −D / ``emission_scale_m`` with D =
E + w·A at the candidate's foot: the edge's way-point nearest the pose, in the candidate's own
direction. (Not the edge's least D: on a curve that way-point slides along the road to wherever the
road's direction matches the heading's error, which both flatters a curved road and moves the
candidate's position by metres a step.) Transitions follow Newson & Krumm (2009): the network
distance between the previous hypothesis and the candidate (each at the pose projected onto its
road), along the edge or through the vertex the previous edge leads to, should equal the distance
the odometry moved; the log-probability is −|d_network − d_odometry| / ``transition_scale_m``.
A jump the graph does not join costs ``jump_penalty`` (so a wrong history can still be left).
The forward filter keeps the ``beam`` most probable hypotheses, normalised to a posterior that
sums to one (:class:`HmmParams`).

It backs ``mapfusion maps stress --sequence``, which matches drives through every junction as
sequences beside the single-frame matcher. A step's answer says whether some candidate's D is under
``lost_cost_m`` (the road explains the pose); a step with no road in range carries the hypotheses
forward along their roads (a wide road's far side or a few metres beyond the radius say nothing
about which road it was).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .roadmap import RoadMap

Key = tuple[int, int]  # (edge, direction: +1 along the drawing direction, −1 against it)


@dataclass(frozen=True)
class HmmParams:
    """The filter's parameters."""

    emission_scale_m: float = 20.0  # m; −D / this is a candidate's log-likelihood: about the D a pose's own errors
    # make (maps stress --sequence, seeds 0–7)
    transition_scale_m: float = 0.5  # m; β of Newson & Krumm 2009 (maps stress --sequence, seeds 0–7)
    jump_penalty: float = 10.0  # log-probability of a transition the road graph does not join
    beam: int = 8  # hypotheses kept after each step (speed)
    lost_cost_m: float = 20.0  # m; a step is unexplained when every candidate's D exceeds this

    def __post_init__(self) -> None:
        if not (self.emission_scale_m > 0 and self.transition_scale_m > 0 and self.jump_penalty >= 0
                and self.beam >= 1 and self.lost_cost_m > 0):
            raise ValueError(f"HmmParams out of range: {self}")


@dataclass(frozen=True)
class Candidate:
    """One (edge, direction) in range: its best way-point, cost D and position along the edge."""

    edge: int
    direction: int
    index: int  # way-point index (-1: carried over a step with no road in range)
    cost: float  # D = E + w·A in this direction
    along_m: float  # s of the way-point along the edge (drawing direction)


@dataclass(frozen=True)
class Step:
    """The filter's answer at one step."""

    best: Candidate | None  # the most probable road, or None without candidates
    posterior: float  # its posterior probability
    hypotheses: int  # how many the beam holds
    explained: bool  # some candidate's D is under lost_cost_m


def candidates(road: RoadMap, near: np.ndarray, x: float, y: float, yaw: float, w: float) -> list[Candidate]:
    """Every (edge, direction) among the way-point indices ``near`` (join curves are not edges and
    are left out), forward then backward, edges ascending. A candidate stands at the foot of the
    pose on its edge (the edge's way-point nearest the pose), its cost the D = E + w·A there and its
    position along the edge the pose projected onto the road's direction there."""
    idx = near[~road.is_join[near]]
    if idx.size == 0:
        return []
    e = np.hypot(road.xy_m[idx, 0] - x, road.xy_m[idx, 1] - y)
    edges = road.edge[idx]
    order = np.lexsort((e, edges))  # by edge, each edge's nearest way-point first (ties: the first in `near`)
    first = np.ones(order.size, dtype=bool)
    first[1:] = edges[order[1:]] != edges[order[:-1]]
    foot = order[first]
    i = idx[foot]
    cos_r, sin_r = road.yaw_cos[i], road.yaw_sin[i]
    a_fwd = np.degrees(np.arccos(np.clip(cos_r * math.cos(yaw) + sin_r * math.sin(yaw), -1.0, 1.0)))
    # along the road's direction at the foot: the way-points' spacing does not step the position
    along = road.s_m[i] + (x - road.xy_m[i, 0]) * cos_r + (y - road.xy_m[i, 1]) * sin_r
    along = np.clip(along, 0.0, road.edge_length_m[edges[foot]])
    rows = list(zip(edges[foot].tolist(), i.tolist(), e[foot].tolist(), a_fwd.tolist(), along.tolist(),
                    road.travel[i].tolist()))
    out = []
    for direction in (1, -1):
        for edge, point, dist, a, s, travel in rows:  # (edges ascending: lexsort's primary key)
            if travel != -direction:  # a one-way edge is a candidate in its legal direction only
                out.append(Candidate(edge, direction, point, dist + w * (a if direction > 0 else 180.0 - a), s))
    return out


class RoadHypotheses:
    """The forward filter over (edge, direction) hypotheses."""

    def __init__(self, road: RoadMap, params: HmmParams = HmmParams()) -> None:
        self.params = params
        self.logp: dict[Key, float] = {}
        self.along: dict[Key, float] = {}
        # as Python lists: the filter reads single entries, a numpy scalar read costs several times more
        self._len = road.edge_length_m.tolist()
        self._u, self._v = road.edge_u.tolist(), road.edge_v.tolist()

    def reset(self) -> None:
        """Forget every hypothesis (after a re-localisation, or when lost)."""
        self.logp.clear()
        self.along.clear()

    def start_on(self, edge: int, direction: int, along_m: float) -> None:
        """Start from a known road (a tracker that arrives localised)."""
        self.logp = {(edge, direction): 0.0}
        self.along = {(edge, direction): along_m}

    def posterior(self) -> dict[Key, float]:
        """The hypotheses' probabilities (they sum to one)."""
        return {k: math.exp(v) for k, v in self.logp.items()}

    def _exit_vertex(self, key: Key) -> int:
        return int(self._v[key[0]] if key[1] > 0 else self._u[key[0]])

    def _network_m(self, prev: Key, s_prev: float, c: Candidate) -> float | None:
        """Distance along the graph from a position on ``prev`` to the candidate, travelling in
        each one's direction: along the same edge, or through the vertex ``prev`` leads to."""
        e0, d0 = prev
        if c.edge == e0 and c.direction == d0:
            return (c.along_m - s_prev) * d0
        v = self._exit_vertex(prev)
        enters = (c.direction > 0 and int(self._u[c.edge]) == v) or (c.direction < 0 and int(self._v[c.edge]) == v)
        if not enters or c.edge == e0:
            return None
        rest = (self._len[e0] - s_prev) if d0 > 0 else s_prev
        into = c.along_m if c.direction > 0 else self._len[c.edge] - c.along_m
        return float(rest + into)

    def step(self, cands: list[Candidate], moved_m: float) -> Step:
        """One forward step with the candidates at the new pose and the odometry's distance since
        the last step."""
        cfg = self.params
        if not cands:
            return self._coast(moved_m)
        emission = {(c.edge, c.direction): -c.cost / cfg.emission_scale_m for c in cands}
        new: dict[Key, float] = {}
        for c in cands:
            key = (c.edge, c.direction)
            if not self.logp:
                new[key] = emission[key]
                continue
            terms = []
            for prev, lp in self.logp.items():
                d = self._network_m(prev, self.along[prev], c)
                trans = -cfg.jump_penalty if d is None else -abs(d - moved_m) / cfg.transition_scale_m
                terms.append(lp + trans)
            new[key] = emission[key] + _logsumexp(terms)
        keep = sorted(new, key=lambda k: new[k], reverse=True)[: cfg.beam]
        norm = _logsumexp([new[k] for k in keep])
        self.logp = {k: new[k] - norm for k in keep}
        by_key = {(c.edge, c.direction): c for c in cands}
        self.along = {k: by_key[k].along_m for k in keep}
        best = by_key[keep[0]]
        explained = min(c.cost for c in cands) <= cfg.lost_cost_m
        return Step(best, math.exp(self.logp[keep[0]]), len(keep), explained)

    def _coast(self, moved_m: float) -> Step:
        """A step with no road in range: the hypotheses carried forward along their roads unchanged
        (a gap of a few metres in the map's reach says nothing about which road it was)."""
        if not self.logp:
            return Step(None, 0.0, 0, False)
        for (edge, direction), s in self.along.items():
            self.along[(edge, direction)] = min(max(s + direction * moved_m, 0.0), self._len[edge])
        key = max(self.logp, key=lambda k: self.logp[k])
        best = Candidate(key[0], key[1], -1, math.inf, self.along[key])
        return Step(best, math.exp(self.logp[key]), len(self.logp), False)


def _logsumexp(values: list[float]) -> float:
    m = max(values)
    if m == -math.inf:
        return m
    return m + math.log(sum(math.exp(v - m) for v in values))
