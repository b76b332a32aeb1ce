"""FusionConfig: docs/configuration.md lists every field with the code's default, and faithful() is the paper's reading."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from mapfusion.config import Backend, FusionConfig, PriorMode, RobustKernel, StateModel, describe

PAGE = Path(__file__).parents[2] / "docs" / "configuration.md"


def test_every_field_is_documented_with_unit_and_source_and_the_page_lists_it():
    text = PAGE.read_text()
    section = text[text.index("## `[mapfusion]`"):text.index("## Scenario")]
    rows = dict(re.findall(r"^\| `(\w+)` \| ([^|]+?) \|", section, flags=re.M))
    fields = {name: default for name, _t, default, _u, _d in describe(FusionConfig)}
    assert set(rows) == set(fields), set(rows) ^ set(fields)
    for name, default in fields.items():
        assert rows[name] == str(default), f"docs/configuration.md says {name} = {rows[name]}, the code {default}"
    for name, _t, _default, _unit, doc in describe(FusionConfig):
        assert doc, f"FusionConfig.{name} has no documentation"


def test_faithful_is_the_papers_direct_reading():
    f = FusionConfig.faithful()
    assert (f.state, f.prior_mode, f.robust_kernel, f.backend) == (StateModel.pose3, PriorMode.paper,
                                                                   RobustKernel.none, Backend.isam2)
    assert f.prior_on_joins and f.prior_ambiguity_m == 0 and f.prior_max_angle_deg == 180
    assert not f.refine_scale and f.loose_before_init
    # the paper's numbers are the defaults of both
    d = FusionConfig()
    for k in ("lane_width_m", "yaw_sigma_deg", "angle_weight_m_per_deg", "search_radius_m", "scale_samples"):
        assert getattr(f, k) == getattr(d, k)


def test_no_number_field_takes_an_absurd_value():
    """Issue 19: a value of 1e308 in any number field is refused at load (it crashed the run after
    it); 1e9, the generic maximum, is still a value."""
    import dataclasses
    import typing

    from mapfusion.config import GENERIC_MAX, FusionConfig, from_mapping
    from mapfusion.errors import ConfigError

    hints = typing.get_type_hints(FusionConfig)
    floats = [f for f in dataclasses.fields(FusionConfig) if hints[f.name] is float]
    assert floats
    for f in floats:
        with pytest.raises(ConfigError, match=f.name):
            from_mapping(FusionConfig, {f.name: 1e308}, "t.toml")
        if f.metadata.get("max") is None:
            assert getattr(from_mapping(FusionConfig, {f.name: GENERIC_MAX}, "t.toml"), f.name) == GENERIC_MAX


def test_a_mode_given_by_name_is_that_mode_and_a_wrong_name_is_refused():
    import dataclasses
    import enum

    from mapfusion.config import PriorTarget, StateModel
    from mapfusion.errors import ConfigError

    # the engine compares modes by identity: a name left as a string would silently take another branch
    c = FusionConfig(prior_target="band", state="pose3")
    assert c.prior_target is PriorTarget.band and c.state is StateModel.pose3
    assert dataclasses.replace(c, state="planar").state is StateModel.planar
    for f in dataclasses.fields(FusionConfig):
        v = getattr(FusionConfig(), f.name)
        if isinstance(v, enum.Enum):
            for member in type(v):
                assert getattr(FusionConfig(**{f.name: member.value}), f.name) is member
    with pytest.raises(ConfigError, match="prior_target = 'sideways' is not one of centre, edge, band"):
        FusionConfig(prior_target="sideways")


@pytest.mark.parametrize("key, says", [("hmm_lost_after_m", "is renamed lost_after_m"),
                                       ("road_tracking", "was removed"), ("hmm_beam", "was removed"),
                                       ("outage_s", "is no longer a setting: fixed as mapfusion.track.OUTAGE_S = 1.0 s"),
                                       ("reloc_step_m", "is no longer a setting: fixed as "
                                                        "mapfusion.relocalise.ParticleParams.step_m = 5.0 m"),
                                       ("gps_reach_back", "was removed: a GPS re-localisation always mends")])
def test_a_retired_key_is_refused_with_one_line_saying_what_became_of_it(tmp_path, key, says):
    from mapfusion.config import from_mapping
    from mapfusion.errors import ConfigError

    assert key not in {f.name for f in dataclasses.fields(FusionConfig)}
    with pytest.raises(ConfigError) as err:
        from_mapping(FusionConfig, {key: 1, "lane_width_m": 3.0}, "old.toml", "mapfusion.")
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"old.toml: mapfusion.{key} {says}")


def test_no_retired_key_is_a_field():
    """A key cannot be both retired and live: the loader would refuse a field the engine reads."""
    assert not set(FusionConfig.RETIRED_KEYS) & {f.name for f in dataclasses.fields(FusionConfig)}


def test_the_engine_has_at_most_80_settings():
    """Issue 67: few knobs. The values fixed by measurement live beside the code that uses them."""
    assert len(dataclasses.fields(FusionConfig)) <= 80


_FIXED_AS = re.compile(r"is no longer a setting: fixed as (mapfusion\.[\w.]+) = (\S+)")
FIXED = {k: m.groups() for k, v in FusionConfig.RETIRED_KEYS.items() if (m := _FIXED_AS.match(v))}


@pytest.mark.parametrize("key", sorted(FIXED))
def test_every_fixed_value_named_by_a_retired_key_exists_with_that_value(key):
    """A retired key that says where its value lives now names a value that is there, as stated: the message
    cannot drift from the code."""
    import importlib

    where, value = FIXED[key]
    parts = where.split(".")
    obj = importlib.import_module(".".join(parts[:2]))
    for name in parts[2:]:
        obj = getattr(obj, name)  # (a dataclass's field: its default, the class attribute)
    assert repr(obj) == value, (key, obj)
