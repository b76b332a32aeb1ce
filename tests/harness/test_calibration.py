"""The calibration harness's own command line and its sensor overrides (issue 22: measuring what a
sensor model would give against the paper's odometry-only ranges)."""

from __future__ import annotations

import dataclasses

import pytest

from mapfusion.harness.calibration import CASES, _parse_case, _parse_override, calibration_runs, main, summarise
from sim.sensors import OdometryParams


@pytest.mark.parametrize("argv", [["--case", "rain:xx"], ["--case", "clear:vo:tunnel"], ["--odometry", "nope=1"],
                                  ["--odometry", "rotation_noise_rad"], ["--odometry", "rotation_noise_rad=abc"],
                                  ["--seeds", "1,x"]])
def test_bad_arguments_exit_with_code_2_and_one_line(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")


def test_every_case_parses_back_to_itself():
    for weather, kind, zone in CASES:
        text = f"{weather}:{kind}" + (":tunnel" if zone is not None else "")
        assert _parse_case(text) == (weather, kind, zone)


def test_every_odometry_field_is_an_override():
    for f in dataclasses.fields(OdometryParams):
        if f.type in ("float", float):
            assert _parse_override(f"{f.name}=0.5") == (f.name, 0.5)


@pytest.mark.sumo
def test_an_odometry_override_reaches_the_simulated_sensor():
    # one drive, clear vo as fitted and with its rotation error and drift removed: the heading error is the
    # fitted VO's main cost on these drives (docs/method.md), so its ATE must drop; the same drive, the same seed
    cases = (("clear", "vo", None),)
    fitted = summarise(calibration_runs(maps=("kotka",), seeds=(1,), cases=cases, workers=1), cases)[0]
    kinder = summarise(calibration_runs(maps=("kotka",), seeds=(1,), cases=cases, workers=1,
                                        odometry={"rotation_noise_rad": 0.0, "yaw_bias_sigma_rad_per_m": 0.0}),
                       cases)[0]
    assert fitted["km"] == kinder["km"]
    assert kinder["ates_m"][0] < fitted["ates_m"][0]
