"""The engine is a library below the simulator and the harness (DESIGN "Layout"): it imports
neither, runs where neither SUMO nor ``sim`` can be imported, and keeps its parts small."""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENGINE = sorted(p for p in (REPO / "mapfusion").rglob("*.py") if "harness" not in p.relative_to(REPO).parts)
SIM = sorted((REPO / "sim").rglob("*.py"))
ENGINE_TESTS = sorted((REPO / "tests" / "mapfusion").glob("*.py")) + [REPO / "tests" / "helpers.py"]


def _module(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every module a file imports, anywhere in it (inside functions too), relative ones resolved."""
    tree = ast.parse(path.read_text(), str(path))
    package = _module(path) if path.name == "__init__.py" else _module(path).rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def _offending(paths: list[Path], banned: tuple[str, ...]) -> list[str]:
    bad = []
    for p in paths:
        for m in imports(p):
            if any(m == b or m.startswith(b + ".") for b in banned):
                bad.append(f"{p.relative_to(REPO)} imports {m}")
    return bad


def test_the_import_scanner_sees_relative_and_local_imports(tmp_path):
    assert "mapfusion.harness" in imports(REPO / "mapfusion" / "harness" / "cli.py") or \
        "mapfusion.harness.tables" in imports(REPO / "mapfusion" / "harness" / "cli.py")
    assert "sim.scenario" in imports(REPO / "mapfusion" / "harness" / "cli.py")  # imported inside commands
    assert "mapfusion.factors" in imports(REPO / "mapfusion" / "engine.py")


def test_the_engine_never_imports_sim_the_harness_or_sumo():
    assert ENGINE and not _offending(ENGINE, ("sim", "mapfusion.harness", "libsumo", "traci", "sumolib", "sumo"))


def test_sim_never_imports_the_harness():
    assert SIM and not _offending(SIM, ("mapfusion.harness",))


def test_the_engines_tests_never_import_sim_or_the_harness():
    assert not _offending(ENGINE_TESTS, ("sim", "mapfusion.harness"))


def test_importing_every_engine_module_loads_no_sim():
    mods = [_module(p) for p in ENGINE]
    code = textwrap.dedent(f"""
        import importlib, sys
        for m in {mods!r}:
            importlib.import_module(m)
        loaded = [m for m in sys.modules if m == "sim" or m.startswith(("sim.", "mapfusion.harness", "libsumo", "traci"))]
        assert not loaded, loaded
    """)
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_the_engine_runs_where_sim_and_sumo_cannot_be_imported(tmp_path):
    code = textwrap.dedent(f"""
        import sys, math
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("sim", "libsumo", "traci", "sumolib", "sumo"):
                    raise ImportError("blocked: " + name)
                return None
        sys.meta_path.insert(0, Block())
        import numpy as np
        from mapfusion import FusionConfig, MapFusion, RoadMap
        from pathlib import Path
        from tests.helpers import straight_road, write_osm
        road = RoadMap.from_osm(write_osm(Path({str(tmp_path)!r}), [(straight_road(3000.0, 0.0, (-1500.0, 0.0)),
                                                                    {{"highway": "primary"}})]), cache=False)
        eng = MapFusion(road, FusionConfig(), gps_rate_hz=1.0, odometry_rate_hz=10.0)
        for k in range(1500):
            t = 0.1 * k
            if k % 10 == 0 and t <= 120:
                lat, lon = road.projection.to_geo(-1400.0 + 10.0 * t, 0.0)
                eng.add_gps(t, float(lat), float(lon), None, 1.0)
            rel = np.eye(4); rel[0, 3] = 0.0 if k == 0 else 1.0
            eng.add_odometry(t, rel)
        eng.finish()
        p = eng.estimate()
        assert eng.initialised and abs(p.x() - (-1400.0 + 149.9 * 10.0)) < 5.0 and abs(p.y()) < 3.0, (p.x(), p.y())
        assert not [m for m in sys.modules if m == "sim" or m.startswith("sim.")]
    """)
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def _field_lines(cls: ast.ClassDef) -> int:
    """Lines of a class's documented field declarations (``name: type = param(...)``): a frozen
    configuration's fields are data, not logic, and do not count towards its size."""
    return sum(n.end_lineno - n.lineno + 1 for n in cls.body if isinstance(n, ast.AnnAssign))


@pytest.mark.parametrize("path", ENGINE, ids=lambda p: p.name)
def test_engine_parts_stay_small(path):
    """No class over 300 lines (field declarations aside) and no function over 60 in the engine (issue 15)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        span = node.end_lineno - node.lineno + 1 if hasattr(node, "end_lineno") else 0
        if isinstance(node, ast.ClassDef):
            span -= _field_lines(node)
            assert span <= 300, f"{path.name}: class {node.name} has {span} lines besides its fields"
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            assert span <= 60, f"{path.name}: {node.name} has {span} lines"


def test_every_project_module_an_import_names_exists_in_this_tree():
    """An import of a renamed module fails here even where a stale installation still provides it."""
    files = ENGINE + SIM + sorted((REPO / "mapfusion" / "harness").glob("*.py"))
    known = {_module(p) for p in files}
    missing = []
    for p in files:
        for m in imports(p):
            if m.split(".")[0] not in ("mapfusion", "sim"):
                continue
            # "from pkg import name" yields pkg.name too: a module, or a name defined in pkg
            if m not in known and m.rpartition(".")[0] not in known:
                missing.append(f"{p.relative_to(REPO)} imports {m}")
    assert not missing, missing


#: The run's tally (:class:`~mapfusion.counters.Counters`): every part is handed it to count into, and owns no
#: state through it.
TALLY = "counters"


def _targets(node: ast.AST) -> list[ast.expr]:
    if isinstance(node, ast.Assign):
        out = []
        for t in node.targets:
            out += list(t.elts) if isinstance(t, ast.Tuple) else [t]
        return out
    return [node.target] if isinstance(node, (ast.AnnAssign, ast.AugAssign)) else []


def _made_here(fn: ast.FunctionDef) -> set[str]:
    """Names a function binds to an object it constructs itself (``params = gtsam.ISAM2Params()``)."""
    return {t.id for n in ast.walk(fn) if isinstance(n, ast.Assign) and isinstance(n.value, ast.Call)
            for t in n.targets if isinstance(t, ast.Name)}


def _is_self(node: ast.expr) -> bool:
    return isinstance(node, ast.Name) and node.id == "self"


def ownership_faults(source: str, engine_classes: set[str], name: str = "<source>") -> list[str]:
    """Where a class writes state it does not own: an attribute of ``self`` its ``__init__`` (or, for a dataclass,
    its field list) does not create, or an attribute of another object (not one the method constructs, not the
    tally, not a numpy array's flags); and where a class inherits from another engine class that is not an explicit
    interface (a Protocol) — exceptions aside, whose bases are what callers catch."""
    tree = ast.parse(source)
    faults = []
    interfaces = {c.name for c in ast.walk(tree) if isinstance(c, ast.ClassDef)
                  and any(ast.unparse(b).endswith("Protocol") for b in c.bases)}
    for cls in (c for c in ast.walk(tree) if isinstance(c, ast.ClassDef)):
        bases = [ast.unparse(b) for b in cls.bases]
        exception = any(b.endswith(("Error", "Exception")) for b in bases)
        for b in bases:
            if b in engine_classes and b not in interfaces and not exception:
                faults.append(f"{name}: {cls.name} inherits from the engine class {b}")
        methods = [n for n in cls.body if isinstance(n, ast.FunctionDef)]
        created = {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)} \
            if any("dataclass" in ast.unparse(d) for d in cls.decorator_list) else set()
        for m in (m for m in methods if m.name == "__init__"):
            created |= {t.attr for n in ast.walk(m) for t in _targets(n)
                        if isinstance(t, ast.Attribute) and _is_self(t.value)}
        for m in methods:
            local = _made_here(m)
            for t in (t for n in ast.walk(m) for t in _targets(n) if isinstance(t, ast.Attribute)):
                base = t.value
                if _is_self(base):
                    if t.attr not in created:
                        faults.append(f"{name}: {cls.name}.{m.name} writes self.{t.attr}, not made by __init__")
                    continue
                owner = base.attr if isinstance(base, ast.Attribute) else base.id if isinstance(base, ast.Name) \
                    else ""
                if owner == TALLY or (owner == "flags" and t.attr == "writeable") or owner in local:
                    continue
                faults.append(f"{name}: {cls.name}.{m.name} writes {ast.unparse(t)}, another part's attribute")
    return faults


def _engine_classes() -> set[str]:
    return {c.name for p in ENGINE for c in ast.walk(ast.parse(p.read_text())) if isinstance(c, ast.ClassDef)}


def test_the_ownership_check_finds_a_mixin_and_a_write_into_another_part():
    """The check below can fail: the engine's old shape (a mixin whose methods create the engine's state, a part
    writing another's attribute) is caught; a part that owns its state and tells others through methods is not."""
    mixin = textwrap.dedent("""
        class Reanchoring:
            def _init(self):
                self._road_steps = {}
        class Engine(Reanchoring):
            def __init__(self):
                self.search = None
            def restart(self):
                self.search.active = None
    """)
    faults = ownership_faults(mixin, {"Reanchoring", "Engine"})
    assert any("writes self._road_steps" in f for f in faults)
    assert any("inherits from the engine class Reanchoring" in f for f in faults)
    assert any("writes self.search.active" in f for f in faults)
    parts = textwrap.dedent("""
        from typing import Protocol
        class Steps(Protocol):
            def step(self, k): ...
        class Carry(Steps):
            def __init__(self, counters):
                self.counters, self._steps = counters, {}
            def step(self, k):
                self._steps[k] = k
                self.counters.carried += 1
                params = dict()
                return k
    """)
    assert ownership_faults(parts, {"Steps", "Carry"}) == []


def test_every_engine_part_owns_its_state_and_composes_rather_than_inherits():
    """Issue 67: no class in the engine package writes an attribute its own __init__ does not create, and none
    inherits from another engine class except an explicit interface."""
    classes = _engine_classes()
    faults = [f for p in ENGINE for f in ownership_faults(p.read_text(), classes, p.name)]
    assert not faults, faults
