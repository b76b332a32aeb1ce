"""The picture of a run directory (``mapfusion plot``, ``plot.png``).

Top: the roads in grey, the truth, the odometry baseline and Map-Fusion, GPS fixes, GPS-denied
stretches shaded and map-prior events marked. Bottom: each estimate's online error over the
distance driven, GPS-denied stretches shaded.
"""

from __future__ import annotations

import csv
import json
import tomllib
from pathlib import Path

import numpy as np

from mapfusion.errors import InputError
from mapfusion.formats import read_gps_csv, read_tum
from mapfusion.metrics import associate

FIGSIZE_IN = (12.0, 10.0)
DPI = 100  # → 1200 × 1000 pixels


def _truth(run: Path):
    p = run / "truth.csv"
    if p.exists():
        with open(p, newline="") as f:
            rows = list(csv.DictReader(f))
        t = np.array([float(r["t"]) for r in rows])
        xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        tunnel = np.array([r.get("in_tunnel", "0") == "1" for r in rows])
        return t, xy, tunnel
    t, xyz, _ = read_tum(run / "truth.tum")
    return t, xyz[:, :2], np.zeros(len(t), dtype=bool)


def _json(path: Path) -> dict:
    """A run's JSON file (metrics, fusion events) as a mapping; {} when absent; InputError when broken."""
    from mapfusion.formats import read_text

    if not path.exists():
        return {}
    try:
        data = json.loads(read_text(path, "JSON file", InputError))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}:{exc.lineno}: not valid JSON ({exc.msg})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object")
    return data


def _spans(mask: np.ndarray):
    """(start, end) index pairs of the True runs of a mask."""
    m = np.concatenate(([False], mask, [False])).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    ends = np.flatnonzero(np.diff(m) == -1) - 1
    return list(zip(starts, ends))


def plot_run(run_dir: str | Path, out: str | Path, road=None) -> Path:
    """Draw a run directory to ``out`` (PNG, 1200 × 1000 px)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run_dir)
    if not (run / "truth.csv").exists() and not (run / "truth.tum").exists():
        raise InputError(f"{run}: not a run directory (no truth.csv or truth.tum)")
    ext = Path(out).suffix.lower().lstrip(".")
    formats = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    if ext not in formats:
        raise InputError(f"--out {out}: unknown picture format {ext!r} (known: {', '.join(sorted(formats))})")
    metrics = _json(run / "metrics.json")
    events = _json(run / "fusion_events.json")
    t, xy, tunnel = _truth(run)
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    if road is None and (run / "scenario.toml").exists():
        try:
            from mapfusion.roadmap import RoadMap

            sc = tomllib.loads((run / "scenario.toml").read_text())
            road = RoadMap.from_osm(sc["map"])
        except Exception:  # the picture is still worth drawing without the roads
            road = None
    fig, (ax, ax_err) = plt.subplots(2, 1, figsize=FIGSIZE_IN, dpi=DPI, gridspec_kw={"height_ratios": [3, 1]})
    pad = 150.0
    lo, hi = xy.min(0) - pad, xy.max(0) + pad
    if road is not None:
        keep = np.all((road.xy_m >= lo) & (road.xy_m <= hi), axis=1) & ~road.is_join
        ax.plot(road.xy_m[keep, 0], road.xy_m[keep, 1], ",", color="0.75", zorder=0)
    for a, b in _spans(tunnel):
        ax.plot(xy[a:b + 1, 0], xy[a:b + 1, 1], "-", color="orange", lw=10, alpha=0.35, zorder=1,
                solid_capstyle="butt", label="GPS-denied" if a == _spans(tunnel)[0][0] else None)
        ax_err.axvspan(dist[a], dist[b], color="orange", alpha=0.25)
    ax.plot(xy[:, 0], xy[:, 1], "k-", lw=1.6, label="truth", zorder=3)
    styles = {"estimate_odometry.tum": ("tab:blue", "odometry (no map)"),
              "estimate_mapfusion.tum": ("tab:red", "Map-Fusion")}
    others = ["tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray"]
    for i, other in enumerate(metrics.get("estimators", [])):  # the plug-in estimators, in their order
        styles[f"estimate_{other}.tum"] = (others[i % len(others)], other)
    for name, (color, label) in styles.items():
        p = run / name
        if not p.exists():
            continue
        te, xe, _ = read_tum(p)
        key = name.removeprefix("estimate_").removesuffix(".tum")
        ate = metrics.get(f"ate_{key}_m")
        ax.plot(xe[:, 0], xe[:, 1], "-", color=color, lw=1.0, zorder=4,
                label=label + (f" (ATE {ate:.2f} m)" if ate is not None else ""))
        ia, ib = associate(te, t)
        err = np.hypot(*(xe[ia, :2] - xy[ib]).T)
        ax_err.plot(dist[ib], err, "-", color=color, lw=1.0, label=label)
        if key == "mapfusion" and events:
            ev = events
            tp = np.asarray(ev.get("map_prior_t", []))
            if len(tp):
                ja, _ = associate(te, tp, 1e-3) if len(tp) >= 1 else (np.array([], int), None)
                ax.plot(xe[ja, 0], xe[ja, 1], "o", ms=3, color="tab:red", mfc="none", zorder=5, label="map prior")
                ka, kb = associate(te[ja], t)
                ax_err.plot(dist[kb], np.hypot(*(xe[ja][ka, :2] - xy[kb]).T), "o", ms=3, color="tab:red", mfc="none")
    if (run / "gps.csv").exists():
        g = read_gps_csv(run / "gps.csv")
        if len(g) and road is not None:
            gx, gy = road.projection.to_enu(g.lat_deg, g.lon_deg)
            ax.plot(gx, gy, "+", color="tab:green", ms=5, zorder=2, label=f"GPS fixes ({len(g)})")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    title = metrics.get("scenario", run.name)
    extras = [metrics.get("weather"), metrics.get("odometry"), metrics.get("gps_mode")]
    ax.set_title(f"{title}  ({', '.join(str(x) for x in extras if x)})" if any(extras) else title)
    ax.legend(loc="best", fontsize=8)
    ax_err.set_xlabel("distance driven (m)")
    ax_err.set_ylabel("online error (m)")
    ax_err.grid(alpha=0.3)
    ax_err.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return out
