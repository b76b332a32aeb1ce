"""OSM → SUMO network with netconvert from the ``eclipse-sumo`` wheel, cached by file hash and options.

Each SUMO edge stays traceable to its OSM way (``--output.original-names`` writes an ``origId``
on every lane), and the tunnel / covered / bridge / layer tags survive as edge parameters
(``--osm.all-attributes`` with ``--osm.extra-attributes``). netconvert reads OSM XML only, so
PBF and compressed inputs are first written out as XML with osmium.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import osmium
from pyproj import Transformer

from mapfusion.errors import InputError, MapFusionError
from mapfusion.osm import DRIVABLE_HIGHWAYS, TUNNEL_VALUES, check_osm_path
from mapfusion.roadmap import default_cache_dir, file_sha256

log = logging.getLogger(__name__)


class SimulationError(MapFusionError):
    """SUMO failed (netconvert or the simulation itself)."""


class RouteError(InputError):
    """A route cannot be built: unknown or disconnected edges, or no route long enough."""


def sumo_home() -> Path:
    """The ``sumo`` package directory of the eclipse-sumo wheel (SUMO_HOME)."""
    import importlib.util

    spec = importlib.util.find_spec("sumo")
    if spec is None or not spec.submodule_search_locations:
        raise SimulationError("the eclipse-sumo package is not installed (pip install eclipse-sumo)")
    return Path(list(spec.submodule_search_locations)[0])


def ensure_sumo_env() -> dict[str, str]:
    """Point SUMO_HOME and PROJ's data at the wheel (so no 'Cannot find proj.db'); returns the env.

    pyproj keeps using its own bundled PROJ data whatever PROJ_DATA says, so this is safe for
    the engine in the same process.
    """
    home = sumo_home()
    os.environ.setdefault("SUMO_HOME", str(home))
    proj = home / "data" / "proj"
    if proj.is_dir():
        os.environ.setdefault("PROJ_DATA", str(proj))
        os.environ.setdefault("PROJ_LIB", str(proj))
    return dict(os.environ)


NETCONVERT_OPTIONS: tuple[str, ...] = (
    "--output.original-names",
    "--osm.all-attributes",
    "--osm.extra-attributes", "tunnel,bridge,layer,covered",
    "--keep-edges.by-vclass", "passenger",
    "--keep-edges.by-type", ",".join(f"highway.{h}" for h in DRIVABLE_HIGHWAYS),
    "--keep-edges.components", "1",
    "--junctions.join",
    "--tls.guess-signals",
    "--tls.discard-simple",
    "--tls.join",
    "--roundabouts.guess",
    "--ramps.guess",
    "--no-warnings",
)
NET_FORMAT = 3  # bump when the parsed network or the options change meaning


@dataclass(frozen=True)
class EdgeInfo:
    """A normal (non-internal) SUMO edge."""

    edge_id: str
    osm_way: int  # the first OSM way of the edge; -1 when netconvert made it up
    osm_ways: tuple[int, ...]  # every OSM way netconvert merged into the edge, in order
    length_m: float
    lanes: int
    tunnel: bool
    bridge: bool
    layer: int


@dataclass
class Network:
    """A SUMO network and what the test bed needs to know of it."""

    net_path: Path
    edges: dict[str, EdgeInfo]
    proj_parameter: str
    net_offset: tuple[float, float]
    _to_geo: Transformer | None = None

    def sumo_xy_to_geo(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SUMO network x/y → WGS84 (lat, lon), as ``simulation.convertGeo`` does, vectorised."""
        if self._to_geo is None:
            self._to_geo = Transformer.from_crs(self.proj_parameter, "EPSG:4326", always_xy=True)
        lon, lat = self._to_geo.transform(np.asarray(x) - self.net_offset[0], np.asarray(y) - self.net_offset[1])
        return lat, lon

    @property
    def routable_edges(self) -> list[str]:
        return sorted(self.edges)


def _as_osm_xml(src: Path, workdir: Path) -> Path:
    """netconvert reads plain OSM XML: write PBF / compressed input out with osmium."""
    name = src.name
    if name.endswith(".osm") or name.endswith(".xml"):
        return src
    out = workdir / "input.osm"
    writer = osmium.SimpleWriter(str(out), overwrite=True)

    class _Copy(osmium.SimpleHandler):
        def node(self, n):
            writer.add_node(n)

        def way(self, w):
            writer.add_way(w)

        def relation(self, r):
            writer.add_relation(r)

    try:
        _Copy().apply_file(str(src))
    except RuntimeError as exc:
        raise InputError(f"{src}: not a readable OSM file ({exc})") from None
    finally:
        writer.close()
    return out


def _parse_net(path: Path) -> tuple[dict[str, EdgeInfo], str, tuple[float, float]]:
    edges: dict[str, EdgeInfo] = {}
    proj, offset = "", (0.0, 0.0)
    for _, el in ET.iterparse(path, events=("end",)):
        if el.tag == "location":
            proj = el.get("projParameter", "")
            ox, oy = (float(v) for v in el.get("netOffset", "0,0").split(","))
            offset = (ox, oy)
        elif el.tag == "edge":
            eid = el.get("id", "")
            if el.get("function") == "internal" or eid.startswith(":"):
                el.clear()
                continue
            params = {p.get("key"): p.get("value") for p in el.findall("param")}
            lanes = el.findall("lane")
            orig = None
            for ln in lanes:
                for p in ln.findall("param"):
                    if p.get("key") == "origId":
                        orig = p.get("value")
            try:
                ways = tuple(int(w) for w in (orig or "").split())
            except ValueError:
                ways = ()
            way = ways[0] if ways else -1
            tunnel = params.get("tunnel", "no") in TUNNEL_VALUES or params.get("covered") == "yes"
            bridge = params.get("bridge", "no") not in ("no", "false", "0")
            try:
                layer = int(float(params.get("layer", "0")))
            except ValueError:
                layer = 0
            edges[eid] = EdgeInfo(eid, way, ways, float(lanes[0].get("length", 0.0)) if lanes else 0.0, len(lanes),
                                  tunnel, bridge, layer)
            el.clear()
    if not proj:
        raise SimulationError(f"{path}: the network has no projection (netconvert output expected)")
    return edges, proj, offset


def run_netconvert(args: list[str]) -> subprocess.CompletedProcess:
    """Run the wheel's netconvert with SUMO_HOME and PROJ's data pointed at the wheel."""
    env = ensure_sumo_env()
    return subprocess.run([str(sumo_home() / "bin" / "netconvert"), *args], capture_output=True, text=True, env=env)


def build_network(osm_path: str | Path, cache_dir: Path | None = None, extra_options: tuple[str, ...] = ()) -> Network:
    """The SUMO network of an OSM file, built with netconvert (cached by file hash and options)."""
    src = check_osm_path(osm_path)
    from importlib.metadata import version

    opts = NETCONVERT_OPTIONS + tuple(extra_options)
    key_src = json.dumps({"sha": file_sha256(src), "opts": opts, "sumo": version("eclipse-sumo"), "fmt": NET_FORMAT})
    key = hashlib.sha256(key_src.encode()).hexdigest()[:24]
    cache = (cache_dir or default_cache_dir()) / f"net-{key}.net.xml"
    if not cache.exists():
        cache.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="mapfusion-net-") as tmp:
            xml = _as_osm_xml(src, Path(tmp))
            out = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
            log.info("netconvert %s", src)
            proc = run_netconvert(["--osm-files", str(xml), "--output-file", str(out), *opts])
            if proc.returncode != 0 or not out.exists():
                out.unlink(missing_ok=True)
                lines = (proc.stderr or proc.stdout).strip().splitlines()
                first_error = next((ln for ln in lines if ln.startswith("Error")), lines[-1] if lines else "no output")
                raise SimulationError(f"netconvert failed on {src}: {first_error}")
            os.replace(out, cache)  # atomic: parallel builders never read half a network
    edges, proj, offset = _parse_net(cache)
    if not edges:
        raise InputError(f"{src}: SUMO found no road a passenger car may drive on")
    return Network(cache, edges, proj, offset)
