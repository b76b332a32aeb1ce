"""The documentation agrees with the code: the generated configuration page is current, every
command the README and docs name exists (--help works), and the README stays a short tour."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mapfusion.harness.cli import app
from mapfusion.harness.docs import PAGE, configuration_markdown

REPO = Path(__file__).resolve().parents[2]
runner = CliRunner()


def test_configuration_page_is_current():
    assert PAGE.read_text() == configuration_markdown(), "run: python -m mapfusion.harness.docs"


def _named_commands() -> list[tuple[str, ...]]:
    text = (REPO / "README.md").read_text() + "".join(p.read_text() for p in (REPO / "docs").glob("*.md"))
    found = set()
    for a, b in re.findall(r"`mapfusion ([a-z][a-z-]*)(?: ([a-z][a-z-]*))?", text):
        found.add((a, b) if b else (a,))
    return sorted(found)


def _groups() -> set[str]:
    return {g.name for g in app.registered_groups}


@pytest.mark.parametrize("words", _named_commands(), ids=" ".join)
def test_every_named_command_has_help(words):
    # "mapfusion run PATH" style mentions carry no sub-command: only groups take a second word
    words = words if words[0] in _groups() else words[:1]
    r = runner.invoke(app, [*words, "--help"])
    assert r.exit_code == 0, f"mapfusion {' '.join(words)} --help: {r.output}"


def test_every_command_and_sub_command_of_the_cli_has_help():
    names = [c.name or c.callback.__name__ for c in app.registered_commands]
    assert {"demo", "run", "simulate", "fuse", "evaluate", "sweep", "tune", "plot", "bench"} <= set(names)
    for name in names:
        assert runner.invoke(app, [name, "--help"]).exit_code == 0, name
    for g in app.registered_groups:
        for c in g.typer_instance.registered_commands:
            r = runner.invoke(app, [g.name, c.name or c.callback.__name__, "--help"])
            assert r.exit_code == 0, (g.name, c.name)


def test_an_unknown_command_fails_the_check():
    assert runner.invoke(app, ["nonexistent", "--help"]).exit_code != 0


def test_readme_is_a_short_tour():
    text = (REPO / "README.md").read_text()
    assert len(text.encode()) < 12 * 1024
    assert text.count("```bash") >= 1 and "mapfusion demo" in text
