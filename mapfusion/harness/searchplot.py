"""The picture of a cold start's road-network search (``mapfusion fuse --start-region ... --plot-search``):
the particles over the map at a few moments, from the spread over the region to the converged cluster.

The search is the engine's own (:class:`mapfusion.relocalise.Relocaliser` with the same configuration and
seed, fed the same odometry poses), run again here so that the engine keeps no history of its particles.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfusion.config import FusionConfig
from mapfusion.relocalise import RELOC_SEED, SEARCH_PARTICLES, Located, Region, Relocaliser
from mapfusion.roadmap import RoadMap

#: Particles drawn per panel (a weighted subsample: the picture, not the filter, is thinned).
DRAWN = 4000


@dataclass
class Snapshot:
    driven_m: float
    xy_m: np.ndarray  # (n, 2) particles drawn by weight


def search_snapshots(road: RoadMap, cfg: FusionConfig, region: Region, odo_xy_yaw: np.ndarray,
                     every_m: float = 25.0) -> tuple[list[Snapshot], Located | None]:
    """Run the search over planar odometry poses (N, 3: x, y, yaw, metres) and keep the particles every
    ``every_m`` of driving, up to convergence; returns the snapshots and the answer (None: not found)."""
    reloc = Relocaliser(road, SEARCH_PARTICLES, region, RELOC_SEED, (cfg.reloc_scale_min, cfg.reloc_scale_max))
    rng = np.random.default_rng(0)
    shots: list[Snapshot] = []
    next_m = 0.0
    found = None
    for x, y, yaw in odo_xy_yaw:
        found = reloc.add(float(x), float(y), float(yaw))
        p = reloc.particles
        if len(p) and (p.driven_m >= next_m or found is not None):
            w = np.exp(p.logw)
            pick = rng.choice(len(p), size=min(DRAWN, len(p)), p=w / w.sum())
            shots.append(Snapshot(p.driven_m, p.positions()[pick]))
            next_m = p.driven_m + every_m
        if found is not None:
            break
    return shots, found


def plot_search(road: RoadMap, region: Region, shots: list[Snapshot], found: Located | None, out: str | Path,
                panels: int = 4) -> Path:
    """Four panels (the first snapshot, two between, the last) over the region's roads."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not shots:
        raise ValueError("no snapshot to draw")
    idx = sorted({round(i * (len(shots) - 1) / max(panels - 1, 1)) for i in range(panels)})
    fig, axes = plt.subplots(1, len(idx), figsize=(4.2 * len(idx), 4.6), squeeze=False)
    near = road.query_radius(region.x_m, region.y_m, region.radius_m * 1.1)
    for ax, i in zip(axes[0], idx):
        s = shots[i]
        ax.scatter(road.xy_m[near, 0], road.xy_m[near, 1], s=0.2, c="0.75", lw=0)
        ax.scatter(s.xy_m[:, 0], s.xy_m[:, 1], s=2, c="tab:red", alpha=0.35, lw=0)
        circle = plt.Circle((region.x_m, region.y_m), region.radius_m, fill=False, ls="--", color="0.4")
        ax.add_patch(circle)
        title = f"{s.driven_m:.0f} m driven"
        if i == idx[-1] and found is not None:
            ax.plot(found.x_m, found.y_m, "k+", ms=14, mew=2)
            title += f": found ({100 * found.mass:.0f}% within {found.spread_m:.0f} m)"
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(region.x_m - region.radius_m, region.x_m + region.radius_m)
        ax.set_ylim(region.y_m - region.radius_m, region.y_m + region.radius_m)
        ax.tick_params(labelsize=7)
    fig.suptitle("Road-network search: the particles (red) over the region's roads (grey)", fontsize=10)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
