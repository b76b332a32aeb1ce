"""The README's promise, case by case: bad input to any command exits 2 with exactly one line on
stderr naming the file or option, no traceback, and nothing written anywhere (issue 19).

Each case is (id, arguments, files to create, the words the line must carry). ``{in}`` in an
argument is the folder of valid inputs (a short drive on a synthetic map), ``{d}`` the case's own
working folder, where its bad files are written. The command runs in-process through the console
script's entry point (``main``), so usage errors go through the same path as in a shell.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from mapfusion.harness.cli import main
from tests.helpers import straight_road, synthetic_truth, write_osm

#: A scenario that would run (on the bundled grid map) if nothing else were wrong with the command.
GOOD_SCENARIO = 'name = "ok"\nmap = "grid"\nseed = 1\nduration_s = 30.0\nmin_route_m = 200.0\n'
BOMB = ('<?xml version="1.0"?>\n<!DOCTYPE osm [<!ENTITY a "aaaaaaaaaa">' +
        "".join(f'<!ENTITY {c} "{("&" + p + ";") * 10}">' for p, c in zip("abcdefg", "bcdefgh")) +
        ']>\n<osm version="0.6"><node id="1" lat="60" lon="24"><tag k="x" v="&h;"/></node></osm>\n')


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Valid inputs: a 1.2 km straight road, a drive along it, its odometry, GPS and a config."""
    from mapfusion.formats import write_gps_csv, write_tum, yaw_to_quaternion
    from mapfusion.roadmap import RoadMap

    d = tmp_path_factory.mktemp("inputs")
    m = write_osm(d, [(straight_road(1200.0, origin=(-600.0, 0.0)), {"highway": "primary", "lanes": "2"})])
    road = RoadMap.from_osm(m)
    tr = synthetic_truth("straight", n=900, speed_mps=1.2)  # 108 m at walking pace, well inside the road
    x = tr.x_m - 50.0
    write_tum(d / "odometry.tum", tr.t_s, np.column_stack([x, tr.y_m + 1.5, tr.z_m]), yaw_to_quaternion(tr.yaw_rad))
    write_tum(d / "truth.tum", tr.t_s, np.column_stack([x, tr.y_m + 1.5, tr.z_m]), yaw_to_quaternion(tr.yaw_rad))
    k = slice(0, 600, 10)
    lat, lon = road.projection.to_geo(x[k], tr.y_m[k] + 1.5)
    write_gps_csv(d / "gps.csv", tr.t_s[k], lat, lon, sigma_m=np.full(len(lat), 2.0))
    (d / "config.toml").write_text("[mapfusion]\nlane_width_m = 3.0\n")
    (d / "scenario.toml").write_text(GOOD_SCENARIO)
    return d


def _tum(rows: list[str]) -> str:
    return "# t tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n"


_OK_ROWS = [f"{0.1 * i:.1f} {i * 0.12:.3f} 0 0 0 0 0 1" for i in range(50)]
_GPS_HEAD = "t,lat,lon,alt,sigma_m\n"
_WHEEL_HEAD = "t,speed_mps\n"
_IMU = "t,ax,ay,az,gx,gy,gz\n" + "".join(f"{0.01 * i:.2f},0,0,9.81,0,0,0\n" for i in range(9000))

# (id, argv, files, needles): files are written to the case's folder {d} before the call
CASES: list[tuple[str, list[str], dict[str, str | bytes], list[str]]] = [
    # ---- maps build
    ("build-missing", ["maps", "build", "{d}/none.osm"], {}, ["none.osm"]),
    ("build-directory", ["maps", "build", "{d}/adir.osm"], {"adir.osm/x": ""}, ["adir.osm"]),
    ("build-empty", ["maps", "build", "{d}/e.osm"], {"e.osm": ""}, ["e.osm"]),
    ("build-junk", ["maps", "build", "{d}/j.osm"], {"j.osm": b"\x00\xff\xfe junk \x89PNG"}, ["j.osm"]),
    ("build-truncated-pbf", ["maps", "build", "{d}/t.osm.pbf"], {"t.osm.pbf": b"PBF"}, ["t.osm.pbf"]),
    ("build-no-roads", ["maps", "build", "{d}/n.osm"],
     {"n.osm": '<?xml version="1.0"?><osm version="0.6"><node id="1" lat="60" lon="24"/></osm>'}, ["n.osm"]),
    ("build-entity-bomb", ["maps", "build", "{d}/b.osm"], {"b.osm": BOMB}, ["b.osm"]),
    ("build-unknown-name", ["maps", "build", "atlantis"], {}, ["atlantis"]),
    ("build-spacing-tiny", ["maps", "build", "grid", "--spacing-m", "1e-6"], {}, ["--spacing-m"]),
    ("build-spacing-nan", ["maps", "build", "grid", "--spacing-m", "nan"], {}, ["--spacing-m"]),
    ("build-unknown-option", ["maps", "build", "grid", "--spacing", "2"], {}, ["--spacing"]),
    # ---- maps generate
    ("generate-kind", ["maps", "generate", "spiral", "--out", "{d}/x.osm"], {}, ["spiral"]),
    ("generate-key", ["maps", "generate", "grid", "--out", "{d}/x.osm", "-p", "colz=3"], {}, ["colz"]),
    ("generate-value", ["maps", "generate", "grid", "--out", "{d}/x.osm", "-p", "cols=many"], {}, ["cols"]),
    ("generate-negative", ["maps", "generate", "grid", "--out", "{d}/x.osm", "-p", "cols=-5"], {}, ["cols"]),
    ("generate-nan", ["maps", "generate", "grid", "--out", "{d}/x.osm", "-p", "block_m=nan"], {}, ["block_m"]),
    ("generate-too-big", ["maps", "generate", "city", "--out", "{d}/x.osm", "-p", "width_km=40"], {}, ["width_km"]),
    ("generate-no-equals", ["maps", "generate", "grid", "--out", "{d}/x.osm", "-p", "cols"], {}, ["cols"]),
    ("generate-out-unwritable", ["maps", "generate", "grid", "--out", "/proc/x.osm"], {}, ["/proc/x.osm"]),
    ("generate-out-directory", ["maps", "generate", "grid", "--out", "{d}/od"], {"od/x": ""}, ["od"]),
    # ---- maps stress
    ("stress-missing", ["maps", "stress", "{d}/none.osm"], {}, ["none.osm"]),
    ("stress-radius", ["maps", "stress", "grid", "--radius-m", "0"], {}, ["--radius-m"]),
    ("stress-heading", ["maps", "stress", "grid", "--heading-error-deg", "-5"], {}, ["--heading-error-deg"]),
    ("stress-poses", ["maps", "stress", "grid", "--poses-per-station", "0"], {}, ["--poses-per-station"]),
    ("stress-lane", ["maps", "stress", "grid", "--lane-width-m", "0"], {}, ["--lane-width-m"]),
    # ---- scenarios generate
    ("family-unknown", ["scenarios", "generate", "--family", "snow", "--out", "{d}/f.toml"], {}, ["snow"]),
    ("family-seeds", ["scenarios", "generate", "--family", "rain", "--seeds", "0", "--out", "{d}/f.toml"], {},
     ["--seeds"]),
    ("family-weather", ["scenarios", "generate", "--family", "rain", "--weather", "hail", "--out", "{d}/f.toml"], {},
     ["hail"]),
    ("family-odometry", ["scenarios", "generate", "--family", "rain", "--odometry", "lidar", "--out", "{d}/f.toml"], {},
     ["lidar"]),
    ("family-map", ["scenarios", "generate", "--family", "rain", "--maps", "atlantis", "--out", "{d}/f.toml"], {},
     ["atlantis"]),
    ("family-name", ["scenarios", "generate", "--family", "rain", "--name", "../x", "--out", "{d}/f.toml"], {},
     ["../x"]),
    ("family-out-directory", ["scenarios", "generate", "--family", "rain", "--out", "{d}/od"], {"od/x": ""}, ["od"]),
    # ---- simulate (every check before SUMO starts)
    ("simulate-missing", ["simulate", "{d}/none.toml", "--out", "{d}/r"], {}, ["none.toml"]),
    ("simulate-directory", ["simulate", "{d}/sd", "--out", "{d}/r"], {"sd/x": ""}, ["sd"]),
    ("simulate-binary", ["simulate", "{d}/b.toml", "--out", "{d}/r"], {"b.toml": b"\x00\x01\x02\xff\xfe"}, ["b.toml"]),
    ("simulate-latin1", ["simulate", "{d}/l.toml", "--out", "{d}/r"], {"l.toml": 'name = "caf\xe9"\n'.encode("latin-1")},
     ["l.toml"]),
    ("simulate-syntax", ["simulate", "{d}/s.toml", "--out", "{d}/r"], {"s.toml": "name = \n"}, ["s.toml"]),
    ("simulate-unknown-key", ["simulate", "{d}/s.toml", "--out", "{d}/r"], {"s.toml": GOOD_SCENARIO + "speed = 3\n"},
     ["speed"]),
    ("simulate-duration", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO.replace("30.0", "-1.0")}, ["duration_s"]),
    ("simulate-seed-type", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO.replace("seed = 1", 'seed = "x"')}, ["seed"]),
    ("simulate-step", ["simulate", "{d}/s.toml", "--out", "{d}/r"], {"s.toml": GOOD_SCENARIO + "step_s = 0.0\n"},
     ["step_s"]),
    ("simulate-imu-negative", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[imu]\naccel_noise_density = -1.0\n"}, ["accel_noise_density"]),
    ("simulate-imu-rate", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[imu]\nrate_hz = 1e9\n"}, ["rate_hz"]),
    ("simulate-imu-huge", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[imu]\ngyro_bias_rw = 1e308\n"}, ["gyro_bias_rw"]),
    ("simulate-odometry-nan", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[odometry]\ntranslation_noise_m = nan\n"}, ["translation_noise_m"]),
    ("simulate-odometry-huge", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[odometry]\ntranslation_noise_m = 1e308\n"}, ["translation_noise_m"]),
    ("simulate-odometry-unknown", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[odometry]\nwobble = 1.0\n"}, ["wobble"]),
    ("simulate-gps-sigma", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[gps]\nsigma_m = 1e300\n"}, ["sigma_m"]),
    ("simulate-gps-mode", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + '[gps]\nmode = "sometimes"\n'}, ["sometimes"]),
    ("simulate-weather", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + '[weather]\nkind = "fog"\n'}, ["fog"]),
    ("simulate-traffic", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[traffic]\nbackground_vehicles = -3\n"}, ["background_vehicles"]),
    ("simulate-name", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO.replace('"ok"', '"../../x"')}, ["name"]),
    ("simulate-map", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO.replace('"grid"', '"nosuch.osm"')}, ["nosuch.osm"]),
    ("simulate-tunnel-zone", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[[tunnels]]\nstart_m = 500.0\nend_m = 100.0\n"}, ["end_m"]),
    ("simulate-mapfusion-huge", ["simulate", "{d}/s.toml", "--out", "{d}/r"],
     {"s.toml": GOOD_SCENARIO + "[mapfusion]\nlane_width_m = 1e308\n"}, ["lane_width_m"]),
    ("simulate-truth-missing", ["simulate", "{in}/scenario.toml", "--out", "{d}/r", "--truth", "{d}/none.tum"], {},
     ["none.tum"]),
    ("simulate-family", ["simulate", "{d}/f.toml", "--out", "{d}/r"],
     {"f.toml": '[family]\nname = "f"\n[base]\nmap = "grid"\n'}, ["f.toml"]),
    ("simulate-out-file", ["simulate", "{in}/scenario.toml", "--out", "{d}/r"], {"r": "a file"}, ["--out"]),
    # ---- fuse
    ("fuse-odometry-missing", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/none.tum", "--out", "{d}/e.tum"], {},
     ["none.tum"]),
    ("fuse-odometry-directory", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/od", "--out", "{d}/e.tum"],
     {"od/x": ""}, ["od"]),
    ("fuse-tum-huge", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": _tum(_OK_ROWS[:10] + ["1.0 1e308 0 0 0 0 0 1"] + _OK_ROWS[11:])}, ["o.tum"]),
    ("fuse-tum-nan", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": _tum(_OK_ROWS[:10] + ["1.0 nan 0 0 0 0 0 1"] + _OK_ROWS[11:])}, ["o.tum"]),
    ("fuse-tum-time", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": _tum(_OK_ROWS[:10] + ["0.5 1 0 0 0 0 0 1"] + _OK_ROWS[11:])}, ["o.tum"]),
    ("fuse-tum-columns", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": _tum(_OK_ROWS[:10] + ["1.0 1 0 0 0 0 1"] + _OK_ROWS[11:])}, ["o.tum"]),
    ("fuse-tum-quaternion", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": _tum(_OK_ROWS[:10] + ["1.0 1 0 0 0 0 0 0"] + _OK_ROWS[11:])}, ["o.tum"]),
    ("fuse-tum-binary", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--out", "{d}/e.tum"],
     {"o.tum": b"\xff\xfe\x00\x01" * 20}, ["o.tum"]),
    ("fuse-gps-header", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                         "--out", "{d}/e.tum"], {"g.csv": "time,lat,lon\n0,60.2,24.9\n"}, ["g.csv"]),
    ("fuse-gps-sigma-zero", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                             "--out", "{d}/e.tum"], {"g.csv": _GPS_HEAD + "0,60.2,24.9,,0\n"}, ["g.csv"]),
    ("fuse-gps-sigma-huge", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                             "--out", "{d}/e.tum"], {"g.csv": _GPS_HEAD + "0,60.2,24.9,,1e300\n"}, ["g.csv"]),
    ("fuse-gps-latitude", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                           "--out", "{d}/e.tum"], {"g.csv": _GPS_HEAD + "0,200,24.9,,2\n"}, ["g.csv"]),
    ("fuse-config-missing", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                             "{d}/none.toml", "--out", "{d}/e.tum"], {}, ["none.toml"]),
    ("fuse-config-directory", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                               "{d}/cd", "--out", "{d}/e.tum"], {"cd/x": ""}, ["cd"]),
    ("fuse-config-binary", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                            "{d}/c.toml", "--out", "{d}/e.tum"], {"c.toml": b"\xff\xfe\x00[mapfusion]\x00"}, ["c.toml"]),
    ("fuse-config-unknown", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                             "{d}/c.toml", "--out", "{d}/e.tum"], {"c.toml": "[mapfusion]\nlane_wdth_m = 3\n"},
     ["lane_wdth_m"]),
    ("fuse-config-retired", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                             "{d}/c.toml", "--out", "{d}/e.tum"], {"c.toml": "[mapfusion]\nhmm_lost_after_m = 50\n"},
     ["hmm_lost_after_m", "renamed lost_after_m"]),
    ("fuse-config-huge", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                          "{d}/c.toml", "--out", "{d}/e.tum"], {"c.toml": "[mapfusion]\nyaw_sigma_deg = 1e308\n"},
     ["yaw_sigma_deg"]),
    ("fuse-config-negative", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--config",
                              "{d}/c.toml", "--out", "{d}/e.tum"], {"c.toml": "[mapfusion]\nlane_width_m = -1\n"},
     ["lane_width_m"]),
    ("fuse-plot-search-alone", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                "--plot-search", "{d}/s.png", "--out", "{d}/e.tum"], {}, ["--plot-search"]),
    ("fuse-start-region-two-numbers", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                       "--start-region", "60.2,24.9", "--out", "{d}/e.tum"], {}, ["--start-region"]),
    ("fuse-start-region-radius", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                  "--start-region", "60.2,24.9,-5", "--out", "{d}/e.tum"], {}, ["--start-region"]),
    ("fuse-start-region-off-map", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                   "--start-region", "10,10,1000", "--out", "{d}/e.tum"], {}, ["--start-region"]),
    ("fuse-start-region-not-found", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/o.tum", "--start-region",
                                     "60.2,24.9,500", "--out", "{d}/e.tum"], {"o.tum": _tum(_OK_ROWS)},
     ["start region"]),
    ("fuse-scale-unknown-alone", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                  "--scale-unknown", "--out", "{d}/e.tum"], {}, ["--scale-unknown"]),
    ("fuse-scale-range-upside-down", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                      "--start-region", "60.2,24.9,500", "--scale-unknown", "--scale-range", "2,0.5",
                                      "--out", "{d}/e.tum"], {}, ["--scale-range"]),
    ("fuse-scale-range-one-number", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum",
                                     "--start-region", "60.2,24.9,500", "--scale-unknown", "--scale-range", "2",
                                     "--out", "{d}/e.tum"], {}, ["--scale-range"]),
    ("fuse-format", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--odometry-format", "xyz",
                     "--out", "{d}/e.tum"], {}, ["xyz"]),
    ("fuse-frame", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--odometry-frame", "up",
                    "--out", "{d}/e.tum"], {}, ["up"]),
    ("fuse-kitti-no-times", ["fuse", "--map", "{in}/map.osm", "--odometry", "{d}/p.txt", "--odometry-format", "kitti",
                             "--out", "{d}/e.tum"], {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3}, ["--times"]),
    ("fuse-out-is-input", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--out",
                           "{in}/odometry.tum"], {}, ["--out"]),
    ("fuse-out-directory", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--out", "{d}/od"],
     {"od/x": ""}, ["--out"]),
    ("fuse-gps-until", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps-until-s", "-1",
                        "--out", "{d}/e.tum"], {}, ["--gps-until-s"]),
    ("fuse-imu-header", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--imu", "{d}/i.csv",
                         "--out", "{d}/e.tum"], {"i.csv": "t,a\n0,1\n"}, ["i.csv"]),
    ("fuse-gps-elsewhere", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                            "--out", "{d}/e.tum"],
     {"g.csv": _GPS_HEAD + "".join(f"{t:.1f},-33.86,151.2{t:03.0f},,2\n" for t in range(0, 60, 1))}, ["g.csv"]),
    ("fuse-gps-swapped", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--gps", "{d}/g.csv",
                          "--out", "{d}/e.tum"],
     {"g.csv": _GPS_HEAD + "".join(f"{t:.1f},24.9,60.2{t:03.0f},,2\n" for t in range(0, 60, 1))}, ["g.csv"]),
    ("fuse-other-city", ["fuse", "--map", "kotka", "--odometry", "{in}/odometry.tum", "--gps", "{in}/gps.csv",
                         "--out", "{d}/e.tum"], {}, ["gps.csv"]),
    ("fuse-wheel-no-imu", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--wheel", "{d}/w.csv",
                           "--out", "{d}/e.tum"], {"w.csv": _WHEEL_HEAD + "0,1\n"}, ["--wheel", "--imu"]),
    ("fuse-wheel-negative", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--wheel", "{d}/w.csv",
                             "--imu", "{d}/i.csv", "--out", "{d}/e.tum"],
     {"w.csv": _WHEEL_HEAD + "0,1\n0.02,-1\n", "i.csv": _IMU}, ["w.csv:3", "speed_mps"]),
    ("fuse-wheel-header", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--wheel", "{d}/w.csv",
                           "--imu", "{d}/i.csv", "--out", "{d}/e.tum"],
     {"w.csv": "t,v\n0,1\n", "i.csv": _IMU}, ["w.csv:1"]),
    ("fuse-wheel-another-time", ["fuse", "--map", "{in}/map.osm", "--odometry", "{in}/odometry.tum", "--wheel",
                                 "{d}/w.csv", "--imu", "{d}/i.csv", "--out", "{d}/e.tum"],
     {"w.csv": _WHEEL_HEAD + "".join(f"{1000 + 0.02 * i:.2f},1\n" for i in range(100)), "i.csv": _IMU},
     ["w.csv", "miss"]),
    ("fuse-bag-wheel-no-imu", ["fuse", "--map", "{in}/map.osm", "--bag", "{d}/b.bag", "--odometry-topic", "/odom",
                               "--wheel-topic", "/wheel", "--out", "{d}/e.tum"], {"b.bag": b"not a bag"},
     ["--wheel-topic", "--imu-topic"]),
    # ---- evaluate
    ("evaluate-truth-missing", ["evaluate", "--truth", "{d}/none.tum", "--estimate", "{in}/odometry.tum"], {},
     ["none.tum"]),
    ("evaluate-estimate-empty", ["evaluate", "--truth", "{in}/truth.tum", "--estimate", "{d}/e.tum"], {"e.tum": ""},
     ["e.tum"]),
    ("evaluate-no-overlap", ["evaluate", "--truth", "{in}/truth.tum", "--estimate", "{d}/e.tum"],
     {"e.tum": _tum([f"{1000 + 0.1 * i:.1f} 0 0 0 0 0 0 1" for i in range(20)])}, ["e.tum"]),
    ("evaluate-max-dt", ["evaluate", "--truth", "{in}/truth.tum", "--estimate", "{in}/odometry.tum", "--max-dt-s", "-1"],
     {}, ["--max-dt-s"]),
    ("evaluate-delocalization", ["evaluate", "--truth", "{in}/truth.tum", "--estimate", "{in}/odometry.tum",
                                 "--delocalization-m", "0"], {}, ["--delocalization-m"]),
    # ---- run, sweep, tune
    ("run-missing", ["run", "{d}/none.toml", "--out", "{d}/o"], {}, ["none.toml"]),
    ("run-wheel-unknown", ["run", "{d}/s.toml", "--out", "{d}/o"],
     {"s.toml": GOOD_SCENARIO + '[odometry]\nkind = "vo+wheel"\n[wheel]\nbogus = 1\n'}, ["s.toml", "wheel.bogus"]),
    ("run-wheel-range", ["run", "{d}/s.toml", "--out", "{d}/o"],
     {"s.toml": GOOD_SCENARIO + '[odometry]\nkind = "vo+wheel"\n[wheel]\nscale_error_min = 0.05\n'},
     ["s.toml", "wheel.scale_error_max"]),
    ("run-out-file", ["run", "{in}/scenario.toml", "--out", "{d}/o"], {"o": "a file"}, ["--out"]),
    ("run-estimator-placeholder", ["run", "{d}/s.toml", "--out", "{d}/o"],
     {"s.toml": GOOD_SCENARIO + '[[estimators]]\nname = "mine"\ncommand = "mine {odo} {out}"\n'}, ["s.toml", "{odo}"]),
    ("run-estimator-class", ["run", "{d}/s.toml", "--out", "{d}/o"],
     {"s.toml": GOOD_SCENARIO + '[[estimators]]\nname = "mine"\nuse = "no_such_module_x:Mine"\n'},
     ["no_such_module_x"]),
    ("run-estimator-name", ["run", "{d}/s.toml", "--out", "{d}/o"],
     {"s.toml": GOOD_SCENARIO + '[[estimators]]\nname = "mapfusion"\nuse = "a:B"\n'}, ["s.toml", "mapfusion"]),
    ("run-out-is-input", ["run", "{d}/s.toml", "--out", "{d}/s.toml"], {"s.toml": GOOD_SCENARIO}, ["--out"]),
    ("run-workers", ["run", "{in}/scenario.toml", "--out", "{d}/o", "--workers", "0"], {}, ["--workers"]),
    ("run-scheduler-scheme", ["run", "{in}/scenario.toml", "--out", "{d}/o", "--scheduler", "http://127.0.0.1:1"], {},
     ["--scheduler"]),
    ("run-scheduler-form", ["run", "{in}/scenario.toml", "--out", "{d}/o", "--scheduler", "tcp://"], {},
     ["--scheduler"]),
    ("run-duplicate-names", ["run", "{in}/scenario.toml", "{d}/s.toml", "--out", "{d}/o"], {"s.toml": GOOD_SCENARIO},
     ["ok"]),
    ("run-family-axis", ["run", "{d}/f.toml", "--out", "{d}/o"],
     {"f.toml": '[family]\nname = "f"\naxes = { "gps.sigma_m" = [] }\n[base]\nmap = "grid"\n'}, ["family.axes"]),
    ("run-family-escape", ["run", "{d}/f.toml", "--out", "{d}/o"],
     {"f.toml": '[family]\nname = "../../f"\n[base]\nmap = "grid"\n'}, ["name"]),
    ("sweep-param-unknown", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-p", "wobble=1,2"], {}, ["wobble"]),
    ("sweep-param-value", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-p", "lane_width_m=abc"], {},
     ["lane_width_m"]),
    ("sweep-variant-missing", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-V", "x={d}/none.toml"], {},
     ["none.toml"]),
    ("sweep-variant-unknown", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-V", "bogus"], {}, ["bogus"]),
    ("sweep-out-file", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-p", "lane_width_m=2,3"], {"o": "a file"},
     ["--out"]),
    ("sweep-scheduler-scheme", ["sweep", "{in}/scenario.toml", "--out", "{d}/o", "-p", "lane_width_m=2,3",
                                "--scheduler", "inproc://x"], {}, ["--scheduler"]),
    ("tune-range-order", ["tune", "{in}/scenario.toml", "--out", "{d}/o", "--range", "lane_width_m=5:1"], {},
     ["lane_width_m"]),
    ("tune-range-unknown", ["tune", "{in}/scenario.toml", "--out", "{d}/o", "--range", "wobble=1:2"], {}, ["wobble"]),
    ("tune-storage-scheme", ["tune", "{in}/scenario.toml", "--out", "{d}/o", "--storage", "nosuch://x"], {},
     ["--storage"]),
    ("tune-storage-dir", ["tune", "{in}/scenario.toml", "--out", "{d}/o", "--storage", "sqlite:////no/such/dir/x.db"],
     {}, ["--storage"]),
    ("tune-trials", ["tune", "{in}/scenario.toml", "--out", "{d}/o", "--trials", "0"], {}, ["--trials"]),
    ("tune-out-file", ["tune", "{in}/scenario.toml", "--out", "{d}/o"], {"o": "a file"}, ["--out"]),
    # ---- plot
    ("plot-missing", ["plot", "{d}/none", "--out", "{d}/p.png"], {}, ["none"]),
    ("plot-corrupt-metrics", ["plot", "{d}/r", "--out", "{d}/p.png"],
     {"r/metrics.json": "{not json", "r/truth.tum": _tum(_OK_ROWS), "r/scenario.toml": GOOD_SCENARIO},
     ["metrics.json"]),
    ("plot-extension", ["plot", "{d}/r", "--out", "{d}/p.xyz"],
     {"r/truth.tum": _tum(_OK_ROWS), "r/scenario.toml": GOOD_SCENARIO}, ["p.xyz"]),
    # ---- import kitti
    ("import-poses-missing", ["import", "kitti", "--poses", "{d}/none.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                              "--map", "{in}/map.osm", "--out", "{d}/r"], {"t.txt": "0\n", "g.kml": "<kml/>"},
     ["none.txt"]),
    ("import-kml-broken", ["import", "kitti", "--poses", "{d}/p.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                           "--map", "{in}/map.osm", "--out", "{d}/r"],
     {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "t.txt": "0\n0.1\n0.2\n", "g.kml": "<kml><Document>"}, ["g.kml"]),
    ("import-kml-entity", ["import", "kitti", "--poses", "{d}/p.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                           "--map", "{in}/map.osm", "--out", "{d}/r"],
     {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "t.txt": "0\n0.1\n0.2\n",
      "g.kml": '<?xml version="1.0"?><!DOCTYPE kml [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
               "<kml><LineString><coordinates>&x;</coordinates></LineString></kml>"}, ["g.kml"]),
    ("import-kml-tag-soup", ["import", "kitti", "--poses", "{d}/p.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                             "--map", "{in}/map.osm", "--out", "{d}/r"],
     {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "t.txt": "0\n0.1\n0.2\n",
      "g.kml": "<kml>" + "<LineString>" * 100_000 + "</kml>"}, ["g.kml"]),
    ("import-gps-at", ["import", "kitti", "--poses", "{d}/p.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                       "--map", "{in}/map.osm", "--out", "{d}/r", "--gps-at", "roof"],
     {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "t.txt": "0\n0.1\n0.2\n", "g.kml": "<kml/>"}, ["--gps-at"]),
    ("import-offset-range", ["import", "kitti", "--poses", "{d}/p.txt", "--times", "{d}/t.txt", "--gps", "{d}/g.kml",
                             "--map", "{in}/map.osm", "--out", "{d}/r", "--offset", "-1"],
     {"p.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "t.txt": "0\n0.1\n0.2\n",
      "g.kml": "<kml><LineString><coordinates>24.9,60.17,0 24.9,60.17,0 24.9,60.17,0 24.9,60.17,0"
               "</coordinates></LineString></kml>"}, ["g.kml", "offset -1"]),
    # ---- noise
    ("noise-param-form", ["noise", "{in}/scenario.toml", "--out", "{d}/n.json", "-p", "lane_width_m"], {},
     ["--param", "KEY=VALUE"]),
    ("noise-param-unknown", ["noise", "{in}/scenario.toml", "--out", "{d}/n.json", "-p", "wobble=1"], {}, ["wobble"]),
    ("noise-param-range", ["noise", "{in}/scenario.toml", "--out", "{d}/n.json", "-p", "lane_width_m=-1"], {},
     ["lane_width_m"]),
    ("noise-draws", ["noise", "{in}/scenario.toml", "--out", "{d}/n.json", "--draws", "-1"], {}, ["--draws"]),
    # ---- bench
    ("bench-city", ["bench", "--city-km", "50x50"], {}, ["--city-km"]),
    ("bench-duration", ["bench", "--duration-s", "10"], {}, ["--duration-s"]),
    ("export-not-a-run", ["export", "{d}", "--geojson", "{d}/x.geojson"], {}, ["not a run directory"]),
    ("export-nothing", ["export", "{d}"], {}, ["--geojson"]),
    ("export-out-directory", ["export", "{d}", "--gpx", "{d}/od"], {"od/x": ""}, ["--gpx"]),
    ("odostats-missing", ["odometry-stats", "--truth", "{d}/none.tum", "--odometry", "{in}/odometry.tum"], {},
     ["none.tum"]),
    ("odostats-format", ["odometry-stats", "--truth", "{in}/truth.tum", "--odometry", "{in}/odometry.tum",
                         "--format", "csv"], {}, ["csv"]),
    ("odostats-no-overlap", ["odometry-stats", "--truth", "{in}/truth.tum", "--odometry", "{d}/o.tum"],
     {"o.tum": _tum([f"{1000 + 0.1 * i:.1f} {i} 0 0 0 0 0 1" for i in range(30)])}, ["o.tum"]),
    ("demo-out-file", ["demo", "--out", "{d}/r"], {"r": "a file"}, ["--out"]),
    # ---- the command line itself
    ("unknown-command", ["fly"], {}, ["fly"]),
    ("unknown-option", ["run", "--wrkers", "2", "{in}/scenario.toml", "--out", "{d}/o"], {}, ["--wrkers"]),
    ("missing-option", ["fuse", "--map", "grid"], {}, ["--out"]),
    ("fuse-no-odometry", ["fuse", "--map", "grid", "--out", "{d}/e.tum"], {}, ["--odometry"]),
    ("fuse-odometry-and-bag", ["fuse", "--map", "grid", "--odometry", "{in}/odometry.tum", "--bag", "{d}/b",
                               "--out", "{d}/e.tum"], {"b/x": ""}, ["--bag"]),
    ("fuse-bag-no-topic", ["fuse", "--map", "grid", "--bag", "{d}/b", "--out", "{d}/e.tum"], {"b/x": ""},
     ["--odometry-topic"]),
    ("fuse-bag-not-a-bag", ["fuse", "--map", "grid", "--bag", "{d}/b.bag", "--odometry-topic", "/odom",
                            "--out", "{d}/e.tum"], {"b.bag": "not a bag"}, ["b.bag"]),
    ("fuse-topic-without-bag", ["fuse", "--map", "grid", "--odometry", "{in}/odometry.tum", "--gps-topic", "/gps",
                                "--out", "{d}/e.tum"], {}, ["--bag"]),
    ("fuse-out-bag-exists", ["fuse", "--map", "grid", "--odometry", "{in}/odometry.tum", "--out", "{d}/e.tum",
                             "--out-bag", "{d}/o.bag"], {"o.bag": "x"}, ["--out-bag"]),
    ("import-bag-missing", ["import", "bag", "--bag", "{d}/none.bag", "--odometry-topic", "/odom", "--out", "{d}/r"],
     {}, ["none.bag"]),
    ("import-bag-empty-folder", ["import", "bag", "--bag", "{d}/b", "--odometry-topic", "/odom", "--out", "{d}/r"],
     {"b/x": ""}, ["b"]),
    ("import-bag-out-file", ["import", "bag", "--bag", "{d}/b", "--odometry-topic", "/odom", "--out", "{d}/r"],
     {"b/x": "", "r": "a file"}, ["--out"]),
    ("bad-integer", ["run", "{in}/scenario.toml", "--out", "{d}/o", "-j", "many"], {}, ["--workers"]),
]


def _snapshot(*roots: Path) -> dict[Path, float]:
    return {p: p.stat().st_mtime_ns for r in roots for p in r.rglob("*")}


@pytest.mark.parametrize("case_id,argv,files,needles", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_exit_2(case_id, argv, files, needles, inputs, tmp_path, monkeypatch, capsys):
    d = tmp_path / "case"
    d.mkdir()
    for name, content in files.items():
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    monkeypatch.chdir(d)
    before = _snapshot(d, inputs)
    args = [a.replace("{in}", str(inputs)).replace("{d}", str(d)) for a in argv]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = main(args)
    out, err = capsys.readouterr()
    # a warning Python would print in a shell is a second line on stderr
    shown = [w for w in caught if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning,
                                                               ImportWarning, ResourceWarning))]
    assert not shown, [str(w.message) for w in shown]
    lines = err.strip().splitlines()
    assert code == 2, f"exit {code}; stdout: {out[-500:]}; stderr: {err[-2000:]}"
    assert len(lines) == 1, err
    assert "Traceback" not in err + out
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert _snapshot(d, inputs) == before, "a refused command wrote or touched a file"


def test_the_catalogue_covers_every_command_and_80_cases():
    from mapfusion.harness.cli import app

    assert len(CASES) >= 80
    assert len({c[0] for c in CASES}) == len(CASES)
    import typer.main

    group = typer.main.get_command(app)
    commands = {name for name, cmd in group.commands.items() if not hasattr(cmd, "commands")}
    commands |= {f"{g} {n}" for g, grp in group.commands.items() if hasattr(grp, "commands") for n in grp.commands}
    covered = {" ".join(a for a in c[1][:2] if not a.startswith(("-", "{"))) for c in CASES}
    covered |= {c[1][0] for c in CASES}
    missing = sorted(c for c in commands if c not in covered)
    assert not missing, f"no bad-input case for: {missing}"
