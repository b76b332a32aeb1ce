"""Synthetic OSM maps for tests and stress work, written as valid OSM XML with real tags.

Each generator lays its roads out in local metres around an origin and writes them as WGS84
through the same :class:`~mapfusion.projection.LocalProjection` the rest of the project uses.
The output is deterministic: the same kind and parameters give byte-identical files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .errors import InputError
from .projection import LocalProjection

#: Default origin of the synthetic maps (a fictional place; any origin works).
DEFAULT_ORIGIN = (60.2, 24.9)


class SyntheticKind(str, Enum):
    """The synthetic map kinds ``mapfusion maps generate`` knows."""

    grid = "grid"
    roundabout = "roundabout"
    y_split = "y-split"
    parallel = "parallel"
    tunnel = "tunnel"
    city = "city"


#: Kinds small enough to commit under ``mapfusion/data/maps/synthetic/`` (``city`` is for performance work).
SMALL_KINDS = (
    SyntheticKind.grid,
    SyntheticKind.roundabout,
    SyntheticKind.y_split,
    SyntheticKind.parallel,
    SyntheticKind.tunnel,
)


@dataclass
class OsmBuilder:
    """Collects nodes (shared where two ways meet) and tagged ways, then writes OSM XML."""

    origin: tuple[float, float] = DEFAULT_ORIGIN
    nodes: dict[tuple[int, int], int] = field(default_factory=dict)
    node_xy: list[tuple[float, float]] = field(default_factory=list)
    ways: list[tuple[list[int], dict[str, str]]] = field(default_factory=list)

    def node(self, x_m: float, y_m: float) -> int:
        """The id of the node at (x, y); points within 1 cm are the same node."""
        key = (int(round(x_m * 100)), int(round(y_m * 100)))
        nid = self.nodes.get(key)
        if nid is None:
            nid = len(self.node_xy) + 1
            self.nodes[key] = nid
            self.node_xy.append((float(x_m), float(y_m)))
        return nid

    def way(self, points_m, **tags: str | int) -> None:
        """Add a way through ``points_m`` (sequence of (x, y)) with the given tags."""
        refs = [self.node(x, y) for x, y in points_m]
        dedup = [r for i, r in enumerate(refs) if i == 0 or r != refs[i - 1]]
        if len(dedup) < 2:
            raise ValueError("a way needs two distinct nodes")
        self.ways.append((dedup, {k.replace("__", ":"): str(v) for k, v in tags.items()}))

    def to_xml(self) -> str:
        proj = LocalProjection(*self.origin)
        xy = np.asarray(self.node_xy)
        lat, lon = proj.to_geo(xy[:, 0], xy[:, 1])
        lines = [
            "<?xml version='1.0' encoding='UTF-8'?>",
            '<osm version="0.6" generator="mapfusion-synthetic">',
            f'  <bounds minlat="{lat.min():.7f}" minlon="{lon.min():.7f}" '
            f'maxlat="{lat.max():.7f}" maxlon="{lon.max():.7f}"/>',
        ]
        for i, (la, lo) in enumerate(zip(lat, lon), start=1):
            lines.append(f'  <node id="{i}" version="1" lat="{la:.7f}" lon="{lo:.7f}"/>')
        for wid, (refs, tags) in enumerate(self.ways, start=1):
            lines.append(f'  <way id="{wid}" version="1">')
            lines.extend(f'    <nd ref="{r}"/>' for r in refs)
            lines.extend(f"    <tag k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in sorted(tags.items()))
            lines.append("  </way>")
        lines.append("</osm>")
        return "\n".join(lines) + "\n"


def _line(p0, p1, step_m: float = 50.0) -> list[tuple[float, float]]:
    """Points from p0 to p1 every ``step_m`` (OSM ways carry intermediate nodes too)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(1, int(math.ceil(np.hypot(*(p1 - p0)) / step_m)))
    return [tuple(p0 + (p1 - p0) * k / n) for k in range(n + 1)]


def _arc(center, radius_m: float, a0_rad: float, a1_rad: float, step_m: float = 10.0) -> list[tuple[float, float]]:
    n = max(2, int(math.ceil(abs(a1_rad - a0_rad) * radius_m / step_m)))
    return [
        (center[0] + radius_m * math.cos(a), center[1] + radius_m * math.sin(a))
        for a in np.linspace(a0_rad, a1_rad, n + 1)
    ]


def grid(cols: int = 6, rows: int = 4, block_m: float = 150.0) -> OsmBuilder:
    """A street grid with a diagonal avenue from the south-west to the north-east corner.

    Residential streets (every other one oneway), a secondary street through the middle each
    way, and the primary diagonal, which crosses the grid lines at T, X and six-way junctions.
    """
    b = OsmBuilder()
    w, h = cols * block_m, rows * block_m
    slope = h / w
    # where the diagonal y = slope·x crosses every grid line
    cross_v = {i: i * block_m * slope for i in range(cols + 1)}
    cross_h = {j: j * block_m / slope for j in range(rows + 1)}
    for i in range(cols + 1):
        x = i * block_m
        ys = sorted({j * block_m for j in range(rows + 1)} | {cross_v[i]})
        main = i == cols // 2
        b.way(
            [(x, y) for y in ys],
            highway="secondary" if main else "residential",
            lanes=2 if main else 1,
            name=f"Avenue {i + 1}",
            **({"oneway": "yes"} if (not main and i % 2 == 1) else {}),
        )
    for j in range(rows + 1):
        y = j * block_m
        xs = sorted({i * block_m for i in range(cols + 1)} | {cross_h[j]})
        main = j == rows // 2
        b.way(
            [(x, y) for x in xs],
            highway="secondary" if main else "residential",
            lanes=2 if main else 1,
            name=f"Street {j + 1}",
            **({"oneway": "-1"} if (not main and j % 2 == 1) else {}),
        )
    pts = sorted(
        {(i * block_m, cross_v[i]) for i in range(cols + 1)} | {(cross_h[j], j * block_m) for j in range(rows + 1)}
    )
    b.way(pts, highway="primary", lanes=4, name="Diagonal Avenue", maxspeed=50)
    return b


def roundabout(radius_m: float = 25.0, arm_m: float = 300.0) -> OsmBuilder:
    """A single-lane roundabout (counter-clockwise, oneway) with four irregularly spaced arms."""
    b = OsmBuilder()
    arm_angles_deg = (0.0, 95.0, 190.0, 280.0)
    ring_angles = sorted(set(np.round(np.linspace(0, 360, 37)[:-1], 6)) | set(arm_angles_deg))
    ring = [(radius_m * math.cos(math.radians(a)), radius_m * math.sin(math.radians(a))) for a in ring_angles]
    ring.append(ring[0])
    b.way(ring, highway="primary", junction="roundabout", oneway="yes", lanes=1, name="Ring")
    names = ("North Road", "East Road", "South Road", "West Road")
    for a, name in zip(arm_angles_deg, names):
        u = (math.cos(math.radians(a)), math.sin(math.radians(a)))
        start = (radius_m * u[0], radius_m * u[1])
        end = ((radius_m + arm_m) * u[0], (radius_m + arm_m) * u[1])
        b.way(_line(start, end), highway="secondary", lanes=2, name=name)
    return b


def y_split() -> OsmBuilder:
    """A trunk road with three branches leaving at 15°, 25° and 30° (y-splits)."""
    b = OsmBuilder()
    xs = (-600.0, -200.0, 100.0, 400.0, 800.0)  # the main road has a node at every split
    main = [pt for a, c in zip(xs[:-1], xs[1:]) for pt in _line((a, 0.0), (c, 0.0))[:-1]] + [(xs[-1], 0.0)]
    b.way(main, highway="trunk", lanes=2, name="Main Road", maxspeed=80)
    branches = (
        (-200.0, -15.0, 500.0, "trunk_link", 1),
        (100.0, 25.0, 450.0, "primary", 2),
        (400.0, -30.0, 350.0, "secondary", 1),
    )
    for k, (x0, angle, length, hw, lanes) in enumerate(branches):
        a = math.radians(angle)
        end = (x0 + length * math.cos(a), length * math.sin(a))
        b.way(_line((x0, 0.0), end), highway=hw, lanes=lanes, name=f"Branch {k + 1}")
    return b


def parallel(offset_m: float = 8.0, length_m: float = 500.0) -> OsmBuilder:
    """A primary road with a service road ``offset_m`` beside it for ``length_m``, linked at both ends."""
    if not 6.0 <= offset_m <= 10.0:
        raise InputError(f"parallel: offset_m must be within 6–10 m, got {offset_m}")
    b = OsmBuilder()
    half = length_m / 2
    ramp = 30.0
    # the primary carries a node wherever a ramp or the side street meets it
    stops = [-half - 400, -half - ramp, 0.0, half + ramp, half + 400]
    primary = [pt for a, c in zip(stops[:-1], stops[1:]) for pt in _line((a, 0.0), (c, 0.0))[:-1]] + [(stops[-1], 0.0)]
    b.way(primary, highway="primary", lanes=2, name="Harbour Road")
    b.way(_line((-half, offset_m), (half, offset_m)), highway="service", lanes=1, name="Harbour Service Road")
    b.way([(-half - ramp, 0.0), (-half, offset_m)], highway="service", lanes=1, oneway="no")
    b.way([(half, offset_m), (half + ramp, 0.0)], highway="service", lanes=1, oneway="no")
    b.way(_line((0.0, 0.0), (0.0, -300.0)), highway="residential", lanes=1, name="Dock Street")
    return b


def tunnel(tunnel_m: float = 700.0, bend_deg: float = 40.0, bend_radius_m: float = 300.0) -> OsmBuilder:
    """A primary road through a ``tunnel_m`` tunnel (tunnel=yes, layer=-1) with a bend, and a
    surface street crossing over it (not connected) with a short bridge."""
    if tunnel_m < 600.0:
        raise InputError(f"tunnel: tunnel_m must be at least 600 m, got {tunnel_m}")
    b = OsmBuilder()
    bend = math.radians(bend_deg)
    arc_len = bend * bend_radius_m
    straight = (tunnel_m - arc_len) / 2
    if straight < 50:
        raise InputError("tunnel: the bend is longer than the tunnel")
    approach = [(-600.0, 0.0), (0.0, 0.0)]
    t0 = (0.0, 0.0)
    t1 = (straight, 0.0)
    center = (straight, bend_radius_m)
    arc = _arc(center, bend_radius_m, -math.pi / 2, -math.pi / 2 + bend)
    end_arc = arc[-1]
    d = (math.cos(bend), math.sin(bend))
    t2 = (end_arc[0] + straight * d[0], end_arc[1] + straight * d[1])
    exit_end = (t2[0] + 600.0 * d[0], t2[1] + 600.0 * d[1])
    b.way(_line(approach[0], approach[1]), highway="primary", lanes=2, name="Tunnel Road")
    b.way(
        _line(t0, t1, 25.0) + arc[1:] + _line(end_arc, t2, 25.0)[1:],
        highway="primary",
        lanes=2,
        name="Tunnel Road",
        tunnel="yes",
        layer=-1,
    )
    b.way(_line(t2, exit_end), highway="primary", lanes=2, name="Tunnel Road")
    # a surface street over the tunnel, unconnected to it, with a bridge over a stream
    b.way(_line((150.0, -400.0), (150.0, -20.0)), highway="residential", lanes=1, name="Hill Street")
    b.way([(150.0, -20.0), (150.0, 20.0)], highway="residential", lanes=1, name="Hill Street", bridge="yes", layer=1)
    b.way(_line((150.0, 20.0), (150.0, 400.0)), highway="residential", lanes=1, name="Hill Street")
    b.way(_line((-600.0, 0.0), (-600.0, 400.0)), highway="tertiary", lanes=1, name="West Street")
    return b


def city(
    width_km: float = 10.0, height_km: float = 15.0, block_m: float = 150.0, arterial_every: int = 5
) -> OsmBuilder:
    """A large grid city for performance work (up to 10 km × 15 km): residential blocks with a
    secondary arterial every ``arterial_every`` blocks."""
    if not (0 < width_km <= 10.0 and 0 < height_km <= 15.0):
        raise InputError(f"city: size must be within 10 km × 15 km, got {width_km} × {height_km}")
    if not 30.0 <= block_m <= 2000.0:
        raise InputError(f"city: block_m must be within 30–2000 m, got {block_m}")
    b = OsmBuilder()
    nx = max(1, int(round(width_km * 1000 / block_m)))
    ny = max(1, int(round(height_km * 1000 / block_m)))
    for i in range(nx + 1):
        art = i % arterial_every == 0
        b.way(
            [(i * block_m, j * block_m) for j in range(ny + 1)],
            highway="secondary" if art else "residential",
            lanes=2 if art else 1,
            name=f"{i + 1} Avenue",
        )
    for j in range(ny + 1):
        art = j % arterial_every == 0
        b.way(
            [(i * block_m, j * block_m) for i in range(nx + 1)],
            highway="secondary" if art else "residential",
            lanes=2 if art else 1,
            name=f"{j + 1} Street",
        )
    return b


_GENERATORS = {
    SyntheticKind.grid: grid,
    SyntheticKind.roundabout: roundabout,
    SyntheticKind.y_split: y_split,
    SyntheticKind.parallel: parallel,
    SyntheticKind.tunnel: tunnel,
    SyntheticKind.city: city,
}


def generate(kind: SyntheticKind | str, **params) -> str:
    """OSM XML text of a synthetic map of ``kind`` with the generator's keyword parameters."""
    try:
        k = SyntheticKind(kind)
    except ValueError as exc:
        raise InputError(
            f"unknown synthetic map kind {kind!r} (known: {', '.join(x.value for x in SyntheticKind)})"
        ) from exc
    return _GENERATORS[k](**params).to_xml()  # type: ignore[operator]


def write(kind: SyntheticKind | str, out: str | Path, **params) -> Path:
    """Generate a synthetic map and write it to ``out``."""
    p = Path(out)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(generate(kind, **params), encoding="utf-8")
    return p


def parse_params(kind: SyntheticKind | str, pairs: list[str]) -> dict:
    """``KEY=VALUE`` pairs → keyword arguments of ``kind``'s generator, converted to its
    parameters' types (InputError naming the pair otherwise)."""
    import inspect

    func: Callable[..., OsmBuilder] = _GENERATORS[SyntheticKind(kind)]  # type: ignore[assignment]
    sig = inspect.signature(func)
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise InputError(f"--param {pair!r}: expected KEY=VALUE")
        key, value = (s.strip() for s in pair.split("=", 1))
        if key not in sig.parameters:
            raise InputError(f"--param {key!r}: {func.__name__} takes {', '.join(sig.parameters) or 'no parameters'}")
        default = sig.parameters[key].default
        try:
            v = type(default)(value) if default is not inspect.Parameter.empty else float(value)
        except ValueError as exc:
            raise InputError(f"--param {key}={value!r}: not a {type(default).__name__}") from exc
        lo, hi = PARAM_RANGES[key]
        if not (math.isfinite(v) and lo <= v <= hi):
            raise InputError(f"--param {key}={value!r}: must be within {lo:g}–{hi:g}")
        out[key] = v
    return out


#: The generators' parameters' ranges: beyond them a generator makes no sensible map (a grid of
#: fewer than two streets each way, a road shorter than its junction spacing) or runs for ever.
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "cols": (2, 200), "rows": (2, 200), "block_m": (20.0, 2000.0), "radius_m": (5.0, 500.0),
    "arm_m": (20.0, 5000.0), "offset_m": (6.0, 10.0), "length_m": (50.0, 20000.0), "tunnel_m": (600.0, 10000.0),
    "bend_deg": (0.0, 90.0), "bend_radius_m": (50.0, 5000.0), "width_km": (0.2, 10.0), "height_km": (0.2, 15.0),
    "arterial_every": (1, 100),
}
