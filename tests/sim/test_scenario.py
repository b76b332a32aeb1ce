"""Scenario and family files: defaults, strict validation, expansion, resolved round trip."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.config import FusionConfig, describe
from sim.scenario import (
    GpsConfig,
    GpsMode,
    OdometryKind,
    Scenario,
    ScenarioError,
    TrafficConfig,
    WeatherKind,
    load_family,
    load_scenario,
    scenario_from_dict,
)
from sim.sensors import OdometryParams, odometry_preset


def _write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_every_key_has_a_documented_default():
    for cls in (Scenario, TrafficConfig, GpsConfig, FusionConfig, OdometryParams):
        for name, _tp, default, _unit, doc in describe(cls):
            assert doc, f"{cls.__name__}.{name} has no documentation"
            assert default is not None or name in ("origin_lat_deg",), f"{cls.__name__}.{name} has no default"


def test_design_example_loads(tmp_path):
    p = _write(tmp_path, '''
name = "helsinki-rain-1"
map = "helsinki"
seed = 1
duration_s = 600.0
step_s = 0.1
min_route_m = 1500.0
[traffic]
background_vehicles = 30
[weather]
kind = "rain"
[odometry]
kind = "vo"
scale_error_sigma = 0.01
[gps]
mode = "init_only"
interval_s = 5.0
rate_hz = 1.0
sigma_m = 2.0
deny_in_tunnels = true
[[tunnels]]
start_m = 800.0
end_m = 1300.0
[mapfusion]
lane_width_m = 3.0
yaw_sigma_deg = 10.0
''')
    sc = load_scenario(p)
    assert sc.weather.kind is WeatherKind.rain and sc.odometry.kind is OdometryKind.vo
    assert sc.gps.mode is GpsMode.init_only and sc.traffic.background_vehicles == 30
    assert sc.tunnels[0].end_m == 1300.0 and sc.mapfusion.yaw_sigma_deg == 10.0
    assert dict(sc.odometry.overrides) == {"scale_error_sigma": 0.01}
    assert sc.map.endswith("maps/helsinki.osm.pbf")


@pytest.mark.parametrize(
    "text,needle",
    [
        ('nmae = "x"', "unknown key nmae"),
        ('[gps]\nsigmaa_m = 2.0', "unknown key gps.sigmaa_m"),
        ('[odometry]\nscale_wobble = 1.0', "unknown key odometry.scale_wobble"),
        ('[mapfusion]\nlane_width = 3', "unknown key mapfusion.lane_width"),
        ('seed = "one"', "seed must be a whole number"),
        ('duration_s = "long"', "duration_s must be a number"),
        ('[gps]\nsigma_m = -1.0', "gps.sigma_m must be ≥ 0"),
        ('step_s = 5.0', "step_s must be ≤ 1"),
        ('[weather]\nkind = "snow"', "weather.kind = 'snow' is not one of clear, rain, heavy_rain"),
        ('[gps]\ndeny_in_tunnels = 1', "gps.deny_in_tunnels must be true or false"),
        ('[[tunnels]]\nstart_m = 10.0\nend_m = 5.0', "end_m"),
        ('map = "no/such/map.osm"', "no such map file"),
        ('[mapfusion]\nbackend = "magic"', "mapfusion.backend"),
        ('seed = 1\nseed =', "not valid TOML"),
        ('[kidnap]\nkind = "teleport"', "kidnap.kind"),
        ('[kidnap]\nkind = "gps_bias"\nbias_min_m = 300.0', "kidnap"),
        ('[kidnap]\njump_m = 5.0', "unknown key kidnap.jump_m"),
    ],
)
def test_bad_scenarios_name_key_and_file(tmp_path, text, needle):
    p = _write(tmp_path, text)
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    assert needle in str(exc.value)
    assert str(p) in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path / "nope.toml")


def test_map_relative_to_the_file(tmp_path):
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "m.osm").write_text("<osm/>")
    p = _write(tmp_path, 'map = "maps/m.osm"')
    assert load_scenario(p).map == str((tmp_path / "maps" / "m.osm").resolve())


def test_family_expands_to_the_cartesian_product(tmp_path):
    p = _write(tmp_path, '''
[family]
name = "rain-tunnel"
seeds = [1, 2, 3]
[family.axes]
"weather.kind" = ["clear", "rain", "heavy_rain"]
"odometry.kind" = ["vo", "vio"]
[base]
map = "grid"
''', "f.toml")
    fam = load_family(p)
    assert fam.name == "rain-tunnel" and len(fam.scenarios) == 18
    assert len({s.name for s in fam.scenarios}) == 18
    assert {(s.weather.kind.value, s.odometry.kind.value, s.seed) for s in fam.scenarios} == {
        (w, o, s) for w in ("clear", "rain", "heavy_rain") for o in ("vo", "vio") for s in (1, 2, 3)}
    assert "rain-tunnel-heavy_rain-vio-s3" in {s.name for s in fam.scenarios}


def test_scenario_file_is_a_family_of_one(tmp_path):
    fam = load_family(_write(tmp_path, 'name = "solo"\nmap = "grid"'))
    assert len(fam.scenarios) == 1 and fam.scenarios[0].name == "solo"


def test_bad_family(tmp_path):
    p = _write(tmp_path, '[family]\nname = "f"\nseeds = [1]\n[family.axes]\n"gps.sigmaa_m" = [1.0]\n[base]\nmap = "grid"\n')
    with pytest.raises(ScenarioError, match="gps.sigmaa_m"):
        load_family(p)
    p = _write(tmp_path, '[family]\nname = "f"\nseeds = []\n', "g.toml")
    with pytest.raises(ScenarioError, match="seeds"):
        load_family(p)


@given(
    seed=st.integers(0, 10**6), bg=st.integers(0, 100), sigma=st.floats(0.0, 50.0),
    weather=st.sampled_from(list(WeatherKind)),
    odo=st.sampled_from([k for k in OdometryKind if k is not OdometryKind.recorded]),  # recorded: its own test
    mode=st.sampled_from(list(GpsMode)), lane=st.floats(0.5, 10.0),
    zones=st.lists(st.tuples(st.floats(0, 1e4), st.floats(1.0, 1e3)), max_size=3),
)
def test_resolved_scenario_round_trips(seed, bg, sigma, weather, odo, mode, lane, zones):
    d = {"name": "rt", "map": "grid", "seed": seed, "traffic": {"background_vehicles": bg},
         "weather": {"kind": weather.value}, "odometry": {"kind": odo.value, "rain_noise_factor": 2.0},
         "gps": {"mode": mode.value, "sigma_m": sigma}, "mapfusion": {"lane_width_m": lane},
         "tunnels": [{"start_m": a, "end_m": a + b} for a, b in zones]}
    sc = scenario_from_dict(d, "test")
    again = scenario_from_dict(tomllib.loads(sc.to_toml()), "round trip")
    assert again == sc


def test_presets_differ_as_the_paper_says():
    clear_vo = odometry_preset(OdometryKind.vo, WeatherKind.clear)
    clear_vio = odometry_preset(OdometryKind.vio, WeatherKind.clear)
    rain_vo = odometry_preset(OdometryKind.vo, WeatherKind.rain)
    assert clear_vo.tunnel_lose_track == 1.0 and clear_vio.tunnel_lose_track == 0.0
    assert clear_vio.scale_error_sigma < clear_vo.scale_error_sigma
    assert rain_vo.rain_episode_rate_per_km > 0 and rain_vo.rain_lateral_drift_m_per_m > 0
    assert dataclasses.replace(clear_vo, scale_error_sigma=0.1) == clear_vo.with_overrides((("scale_error_sigma", 0.1),))


# ----------------------------------------------------------------------------- real data and recorded drives
def _fake_kitti(d, map_src=None):
    import shutil

    from tests.helpers import MAPS

    d.mkdir(parents=True, exist_ok=True)
    for f in ("poses.txt", "times.txt", "rtk_gps.kml"):
        (d / f).write_text("")
    shutil.copy(map_src or MAPS / "synthetic" / "grid.osm", d / "map.osm")
    return d


def test_data_paths_expand_and_missing_data_is_unavailable(tmp_path, monkeypatch):
    import os
    import shutil

    from sim.scenario import DataUnavailableError
    from tests.helpers import MAPS

    data = tmp_path / "data"
    (data / "osm").mkdir(parents=True)
    shutil.copy(MAPS / "synthetic" / "grid.osm", data / "osm" / "city.osm")
    p = _write(tmp_path, '[family]\nname = "f"\n[family.axes]\nmap = ["grid", "${MYDATA}/osm/city.osm"]\n')
    monkeypatch.delenv("MYDATA", raising=False)
    fam = load_family(p)
    assert [s.name for s in fam.scenarios] == ["f-grid-s1"]
    assert [n for n, _ in fam.unavailable] == ["f-city-s1"] and "$MYDATA" in fam.unavailable[0][1]
    with pytest.raises(DataUnavailableError, match=r"needs \$MYDATA"):
        load_scenario(_write(tmp_path, 'map = "${MYDATA}/osm/city.osm"', "one.toml"))
    # a relative value is relative to the working directory, not to the family file
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MYDATA", "data")
    fam = load_family(p)
    assert len(fam.scenarios) == 2 and not fam.unavailable
    assert fam.scenarios[1].map == str((data / "osm" / "city.osm").resolve())
    # set, but pointing nowhere: an error, never a silent skip
    monkeypatch.setenv("MYDATA", os.fspath(tmp_path / "nowhere"))
    with pytest.raises(ScenarioError, match="no such map file"):
        load_family(p)


def test_recorded_drive_keys(tmp_path):
    with pytest.raises(ScenarioError, match="needs a recorded drive"):
        scenario_from_dict({"gps": {"source": "recorded"}}, "t")
    with pytest.raises(ScenarioError, match="no such file or directory"):
        scenario_from_dict({"truth": "nope.tum"}, "t", tmp_path)
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "poses.txt").write_text("")
    with pytest.raises(ScenarioError, match="not a KITTI sequence .missing times.txt, rtk_gps.kml"):
        scenario_from_dict({"truth": "half"}, "t", tmp_path)
    seq = _fake_kitti(tmp_path / "seq")
    sc = scenario_from_dict({"truth": "seq", "gps": {"source": "recorded"}}, "t", tmp_path)
    assert sc.map == str((seq / "map.osm").resolve()) and sc.truth == str(seq.resolve())
    assert scenario_from_dict({"truth": "seq", "map": "roundabout"}, "t", tmp_path).map.endswith("roundabout.osm")
    # the resolved scenario round-trips
    assert scenario_from_dict(tomllib.loads(sc.to_toml()), "again") == sc


def test_kitti_family_file_names_runs_by_sequence(tmp_path, monkeypatch):
    from tests.helpers import REPO

    for s in ("00", "01", "02", "05", "07"):
        _fake_kitti(tmp_path / "kitti" / s)
    monkeypatch.setenv("MAPFUSION_DATA", str(tmp_path))
    fam = load_family(REPO / "scenarios" / "families" / "kitti.toml")
    names = {s.name for s in fam.scenarios}
    assert len(names) == 20 and "kitti-00-clear-vo-s1" in names and "kitti-07-rain-vio-s1" in names
    s = next(s for s in fam.scenarios if s.name == "kitti-05-rain-vo-s1")
    assert s.truth == str((tmp_path / "kitti" / "05").resolve()) and s.map.endswith("05/map.osm")
    assert s.gps.source.value == "recorded" and s.gps.mode is GpsMode.init_only and s.weather.kind is WeatherKind.rain


def test_family_zip_varies_its_keys_together_crossed_with_the_axes(tmp_path):
    p = _write(tmp_path, '''
[family]
name = "z"
seeds = [1, 2]
[family.axes]
"weather.kind" = ["clear", "rain"]
[family.zip]
"traffic.background_vehicles" = [0, 5, 9]
"gps.sigma_m" = [1.0, 2.0, 3.0]
[base]
map = "grid"
''', "z.toml")
    fam = load_family(p)
    assert len(fam.scenarios) == 2 * 3 * 2  # axes × zip positions × seeds
    assert {(s.traffic.background_vehicles, s.gps.sigma_m) for s in fam.scenarios} == {(0, 1.0), (5, 2.0), (9, 3.0)}
    assert "z-rain-5-2.0-s2" in {s.name for s in fam.scenarios}
    for bad, needle in (('"gps.sigma_m" = [1.0, 2.0]', "same length"), ('"weather.kind" = ["clear", "rain", "rain"]',
                                                                         "both in family.axes and family.zip")):
        text = p.read_text().replace('"gps.sigma_m" = [1.0, 2.0, 3.0]', bad)
        with pytest.raises(ScenarioError, match=needle):
            load_family(_write(tmp_path, text, "bad.toml"))


def test_a_zipped_list_of_tunnel_zones_names_its_runs_by_the_zones(tmp_path):
    p = _write(tmp_path, '''
[family]
name = "t"
[family.zip]
tunnels = [[], [{ start_m = 100.0, end_m = 250.0 }]]
[base]
map = "grid"
''', "t.toml")
    fam = load_family(p)
    assert {s.name: len(s.tunnels) for s in fam.scenarios} == {"t-none-s1": 0, "t-100.0-250.0-s1": 1}
    assert next(s for s in fam.scenarios if s.tunnels).tunnels[0].end_m == 250.0


def test_recorded_odometry_keys(tmp_path):
    seq = _fake_kitti(tmp_path / "seq")
    (tmp_path / "vo.txt").write_text("")
    with pytest.raises(ScenarioError, match="odometry.file goes with"):
        scenario_from_dict({"truth": "seq", "odometry": {"kind": "recorded"}}, "t", tmp_path)
    with pytest.raises(ScenarioError, match="odometry.file goes with"):
        scenario_from_dict({"truth": "seq", "odometry": {"file": "vo.txt"}}, "t", tmp_path)
    with pytest.raises(ScenarioError, match="needs a recorded drive"):
        scenario_from_dict({"odometry": {"kind": "recorded", "file": "vo.txt"}}, "t", tmp_path)
    with pytest.raises(ScenarioError, match="takes no preset fields"):
        scenario_from_dict({"truth": "seq", "odometry": {"kind": "recorded", "file": "vo.txt", "scale_error_sigma": 0.1}},
                           "t", tmp_path)
    with pytest.raises(ScenarioError, match="odometry.file: .*nope.txt: no such file"):
        scenario_from_dict({"truth": "seq", "odometry": {"kind": "recorded", "file": "nope.txt"}}, "t", tmp_path)
    sc = scenario_from_dict({"truth": "seq", "odometry": {"kind": "recorded", "file": "vo.txt"}}, "t", tmp_path)
    assert sc.odometry.kind is OdometryKind.recorded and sc.odometry.file == str((tmp_path / "vo.txt").resolve())
    assert sc.truth == str(seq.resolve())
    assert scenario_from_dict(tomllib.loads(sc.to_toml()), "again") == sc  # the resolved scenario round-trips


def test_recorded_odometry_is_the_files_poses_at_the_truths_times(tmp_path):
    import numpy as np

    from mapfusion.formats import FormatError
    from mapfusion.replay import camera_to_body
    from sim.sensors import recorded_odometry
    from tests.helpers import synthetic_truth

    truth = synthetic_truth("random", n=50, seed=3)
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (60, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 1, (60, 3)), axis=0)
    (tmp_path / "vo.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in p[:3].ravel()) for p in poses) + "\n")
    odo = recorded_odometry(truth, str(tmp_path / "vo.txt"))
    np.testing.assert_allclose(odo.poses, camera_to_body(poses[:50]), atol=1e-8)  # the drive's first 50 frames
    np.testing.assert_array_equal(odo.t_s, truth.t_s)
    np.testing.assert_array_equal(odo.frame_index, np.arange(50))
    with pytest.raises(FormatError, match="30 poses, but the recorded drive has 50 frames"):
        (tmp_path / "short.txt").write_text("\n".join((tmp_path / "vo.txt").read_text().splitlines()[:30]) + "\n")
        recorded_odometry(truth, str(tmp_path / "short.txt"))


def test_kitti_real_family_pairs_each_result_with_its_drive(tmp_path, monkeypatch):
    from tests.helpers import REPO

    for s in ("00", "01", "02", "05", "07"):
        _fake_kitti(tmp_path / "kitti" / s)
    (tmp_path / "vo").mkdir()
    for s in ("00", "01", "02", "05", "07"):
        for m in ("cvo_stereo", "trianflow"):
            (tmp_path / "vo" / f"{m}_{s}.txt").write_text("")
    monkeypatch.setenv("MAPFUSION_DATA", str(tmp_path))
    fam = load_family(REPO / "scenarios" / "families" / "kitti-real.toml")
    assert len(fam.scenarios) == 10
    for sc in fam.scenarios:
        seq = sc.name.split("-")[2]
        assert sc.truth.endswith(f"kitti/{seq}") and sc.odometry.file.endswith(f"_{seq}.txt")
        assert sc.odometry.kind is OdometryKind.recorded and sc.gps.init_window_s == 30.0


def test_a_kidnap_table_is_read_and_written_only_when_there_is_one(tmp_path):
    sc = load_scenario(_write(tmp_path, '[kidnap]\nkind = "vo_jump"\njump_min_m = 40.0\njump_max_m = 80.0\n'))
    assert sc.kidnap.kind.value == "vo_jump" and sc.kidnap.jump_min_m == 40.0
    assert tomllib.loads(sc.to_toml())["kidnap"]["jump_max_m"] == 80.0
    plain = load_scenario(_write(tmp_path, 'seed = 3\n', "plain.toml"))
    assert "kidnap" not in tomllib.loads(plain.to_toml())  # (unchanged files and hashes for every other drive)
