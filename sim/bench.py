"""Simulation throughput: simulated seconds per wall-clock second on Helsinki."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from mapfusion.maps import resolve_map
from mapfusion.roadmap import RoadMap

from .drive import run_drive
from .network import build_network
from .scenario import scenario_from_dict


@dataclass(frozen=True)
class SimBench:
    map: str
    vehicles: int
    fleet: bool
    sim_s: float
    wall_s: float
    realtime_factor: float

    def to_dict(self) -> dict:
        return asdict(self)


def bench_sim(background_vehicles: int, fleet: bool = False, duration_s: float = 600.0, seed: int = 1,
              map_name: str = "helsinki") -> SimBench:
    """One drive of ``duration_s`` with ``background_vehicles`` others (network build excluded)."""
    path = resolve_map(map_name)
    road = RoadMap.from_osm(path)
    net = build_network(path)
    sc = scenario_from_dict({"name": "bench", "map": str(path), "seed": seed, "duration_s": duration_s,
                             "min_route_m": 100000.0, "route": {"max_trips": 200},
                             "traffic": {"background_vehicles": background_vehicles, "fleet": fleet}}, "bench")
    d = run_drive(sc, road, net)
    return SimBench(map=str(path), vehicles=d.vehicles, fleet=fleet, sim_s=d.sim_s, wall_s=d.wall_s,
                    realtime_factor=d.realtime_factor)
