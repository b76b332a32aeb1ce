"""The bundled maps: package data, found by name from any folder and any install."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

import mapfusion
from mapfusion import MapFileError
from mapfusion.maps import BUILTIN_MAPS, maps_dir, resolve_map

PACKAGE = Path(mapfusion.__file__).resolve().parent


def test_the_bundled_maps_are_inside_the_package_and_every_name_resolves(tmp_path, monkeypatch):
    monkeypatch.delenv("MAPFUSION_MAPS", raising=False)
    monkeypatch.chdir(tmp_path)  # (an empty folder: nothing is found relative to the current one)
    assert maps_dir() == PACKAGE / "data" / "maps"
    for name, file in BUILTIN_MAPS.items():
        p = resolve_map(name)
        assert p == maps_dir() / file and p.is_file(), name
    with pytest.raises(MapFileError, match="atlantis"):
        resolve_map("atlantis")


def test_mapfusion_maps_points_elsewhere(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPFUSION_MAPS", str(tmp_path))
    assert resolve_map("grid") == tmp_path / BUILTIN_MAPS["grid"]


def test_the_wheel_takes_every_bundled_file():
    """pyproject's package-data globs cover every file under mapfusion/data/maps (a map added there without a glob
    would be missing from an installed wheel, and only there)."""
    cfg = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())
    globs = cfg["tool"]["setuptools"]["package-data"]["mapfusion"]
    taken = {p for g in globs for p in PACKAGE.glob(g)}
    bundled = {p for p in (PACKAGE / "data" / "maps").rglob("*") if p.is_file()}
    assert bundled and bundled <= taken, sorted(str(p) for p in bundled - taken)


def test_a_scenario_in_the_checkout_may_name_maps_relative_to_itself():
    """DESIGN's scenario example: ``map = "maps/helsinki.osm.pbf"`` relative to the file, at the repository root."""
    root = PACKAGE.parent
    assert resolve_map("maps/helsinki.osm.pbf", base_dir=root).resolve() == (maps_dir() / "helsinki.osm.pbf").resolve()
