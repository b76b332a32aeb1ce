"""The results of a run: one typed record owns the ``metrics.json`` / ``results.jsonl`` keys
(DESIGN "File formats", contract), and one function owns the averaging every table uses.

A row is a plain dict on disk (JSON); :class:`Estimator` names the two estimates every run scores
(the odometry baseline and Map-Fusion) and :func:`estimator_metrics` builds their keys, so no key
is spelled out by hand elsewhere. :func:`summarise` averages a set of rows two ways: over every
run, and as the paper's tables do (de-localised runs left out, the reduction over runs where
neither estimate is de-localised).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mapfusion.metrics import OnlineError


class Estimator(str, enum.Enum):
    """The two estimates a run scores, by their key infix."""

    odometry = "odometry"  # the baseline: the same engine with map priors off
    mapfusion = "mapfusion"


def ate_key(e: Estimator | str) -> str:
    return f"ate_{e.value if isinstance(e, Estimator) else e}_m"


def delocalized_key(e: Estimator | str) -> str:
    return f"delocalized_{e.value if isinstance(e, Estimator) else e}"


def estimator_metrics(e: Estimator | str, ate_m: float, delocalized: bool, online: OnlineError,
                      tunnel_rmse_m: float | None, rpe_100m_m: float | None) -> dict:
    """The contract's per-estimator keys of one run (``e``: one of the two, or a plug-in's name)."""
    v = e.value if isinstance(e, Estimator) else e
    return {ate_key(e): ate_m, delocalized_key(e): delocalized,
            f"online_rmse_{v}_m": online.rmse_m, f"online_max_{v}_m": online.max_m, f"online_end_{v}_m": online.end_m,
            f"online_lateral_rmse_{v}_m": online.lateral_rmse_m,
            f"online_longitudinal_rmse_{v}_m": online.longitudinal_rmse_m,
            f"tunnel_rmse_{v}_m": tunnel_rmse_m, f"rpe_100m_{v}_m": rpe_100m_m}


#: Keys every finished row holds (DESIGN "File formats"); a failed row holds ``error`` instead of the scores.
REQUIRED_KEYS = ("scenario", "seed", "map", "weather", "odometry", "gps_mode", "route_length_m", "duration_s", "frames",
                 "ate_odometry_m", "ate_mapfusion_m", "ate_reduction_m", "delocalized_odometry",
                 "delocalized_mapfusion", "online_rmse_odometry_m", "online_rmse_mapfusion_m", "online_max_mapfusion_m",
                 "tunnel_rmse_mapfusion_m", "match_rate", "map_priors", "fusion_frames_per_s")


def finished(row: dict) -> bool:
    """The row scored both estimates (it did not fail)."""
    return "error" not in row and ate_key(Estimator.odometry) in row


@dataclass(frozen=True)
class Summary:
    """Averages of a set of runs (ATE in m)."""

    runs: int
    failed: int
    mean_odometry_m: float  # over every finished run
    mean_mapfusion_m: float
    delocalized_odometry: int
    delocalized_mapfusion: int
    paper_odometry_m: float  # the paper's average: de-localised runs left out
    paper_mapfusion_m: float
    paper_reduction_m: float  # over runs where neither is de-localised

    @property
    def reduction_fraction(self) -> float:
        """1 − mean Map-Fusion / mean odometry ATE, over every finished run."""
        return 1.0 - self.mean_mapfusion_m / self.mean_odometry_m if self.mean_odometry_m > 0 else math.nan


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def summarise(rows: Iterable[dict]) -> Summary:
    """Every table's averages of ``rows`` (see :class:`Summary`)."""
    rows = list(rows)
    ok = [r for r in rows if finished(r)]
    o, m = Estimator.odometry, Estimator.mapfusion
    kept_o = [r[ate_key(o)] for r in ok if not r[delocalized_key(o)]]
    kept_m = [r[ate_key(m)] for r in ok if not r[delocalized_key(m)]]
    both = [r[ate_key(o)] - r[ate_key(m)] for r in ok if not r[delocalized_key(o)] and not r[delocalized_key(m)]]
    return Summary(runs=len(ok), failed=len(rows) - len(ok),
                   mean_odometry_m=_mean([r[ate_key(o)] for r in ok]), mean_mapfusion_m=_mean([r[ate_key(m)] for r in ok]),
                   delocalized_odometry=sum(bool(r[delocalized_key(o)]) for r in ok),
                   delocalized_mapfusion=sum(bool(r[delocalized_key(m)]) for r in ok),
                   paper_odometry_m=_mean(kept_o), paper_mapfusion_m=_mean(kept_m), paper_reduction_m=_mean(both))


def non_finite_to_none(row: dict) -> dict:
    """JSON has no NaN or infinity: such a figure is null."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
