"""Shared by tests/ and scenarios/: hypothesis profiles and an isolated cache.

Hypothesis loads its built-in ``ci`` profile by itself when ``CI=true``; elsewhere the ``dev``
profile below applies (fewer examples, no deadline: the machines are noisy).
"""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

settings.register_profile("dev", max_examples=40, deadline=None)
if os.environ.get("HYPOTHESIS_PROFILE"):
    settings.load_profile(os.environ["HYPOTHESIS_PROFILE"])
elif not os.environ.get("CI"):
    settings.load_profile("dev")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """pytest-xdist's ``loadgroup``: a test with no group of its own goes with the others of its file (as
    ``loadfile`` would: a module's expensive fixtures are built once); the scenario families group by family."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    """Road-map and network caches of a test run go to a temporary folder, never the user's cache."""
    old = os.environ.get("MAPFUSION_CACHE")
    os.environ["MAPFUSION_CACHE"] = str(tmp_path_factory.mktemp("mapfusion-cache"))
    yield
    if old is None:
        os.environ.pop("MAPFUSION_CACHE", None)
    else:
        os.environ["MAPFUSION_CACHE"] = old
