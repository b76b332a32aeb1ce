"""Where the bundled maps live, and built-in map names (``helsinki``, ``kotka``, ``synthetic/grid`` ...)."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from .errors import MapFileError

#: Built-in names → file names under the maps directory.
BUILTIN_MAPS: dict[str, str] = {
    "helsinki": "helsinki.osm.pbf",
    "kotka": "kotka.osm.pbf",
    "grid": "synthetic/grid.osm",
    "roundabout": "synthetic/roundabout.osm",
    "y-split": "synthetic/y-split.osm",
    "parallel": "synthetic/parallel.osm",
    "tunnel": "synthetic/tunnel.osm",
}


def maps_dir() -> Path:
    """The bundled maps: ``$MAPFUSION_MAPS``, else the package's own ``mapfusion/data/maps`` (package data: in a
    checkout, an editable install and an installed wheel alike)."""
    env = os.environ.get("MAPFUSION_MAPS")
    if env:
        return Path(env)
    here = resources.files("mapfusion").joinpath("data", "maps")
    if not isinstance(here, Path):  # a zipped install: the maps are not files netconvert could read
        raise MapFileError(f"the bundled maps are inside {here} (not on the file system): set MAPFUSION_MAPS")
    return here


def resolve_map(name_or_path: str | os.PathLike, base_dir: Path | None = None) -> Path:
    """A map path from a built-in name, a path relative to ``base_dir`` (or the cwd), or an absolute path.

    Raises :class:`MapFileError` naming what was tried when nothing matches.
    """
    s = str(name_or_path)
    key = s.removeprefix("synthetic/") if s.startswith("synthetic/") and not s.endswith(".osm") else s
    if key in BUILTIN_MAPS:
        return maps_dir() / BUILTIN_MAPS[key]
    p = Path(s).expanduser()
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    if p.exists():
        return p
    raise MapFileError(
        f"{s}: no such map file, and not a built-in map name ({', '.join(sorted(BUILTIN_MAPS))})"
    )
