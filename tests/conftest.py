"""Fixtures of the unit tests (profiles and cache isolation live in the root conftest.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def helsinki():
    from mapfusion import RoadMap

    return RoadMap.from_osm(REPO / "mapfusion" / "data" / "maps" / "helsinki.osm.pbf")
