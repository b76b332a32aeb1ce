"""ROS bags (issue 20): a simulated run written to ROS 2 (mcap, sqlite3) and ROS 1 bags, fused from
the bag, gives the run directory's estimate; --out-bag reads back; bad bags are one line, exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from mapfusion.bags import BagKind, read_bag, write_bag
from mapfusion.formats import read_gps_csv, read_imu_csv, read_tum, tum_to_matrices
from mapfusion.harness.cli import main
from tests.harness.sim_helpers import simulated_grid_run

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return simulated_grid_run(tmp_path_factory.mktemp("bagrun"), "bag", 5)


def _bag_of(run, path, kind: BagKind, child_frame: str = "base_link"):
    t, xyz, q = read_tum(run / "odometry.tum")
    return write_bag(path, kind, (t, tum_to_matrices(xyz, q)), read_gps_csv(run / "gps.csv"),
                     read_imu_csv(run / "imu.csv"), child_frame=child_frame)


@pytest.mark.parametrize("kind", list(BagKind), ids=lambda k: k.value)
def test_a_bag_reads_back_what_was_written(run_dir, tmp_path, kind):
    bag = _bag_of(run_dir, tmp_path / ("b.bag" if kind is BagKind.ros1 else "b"), kind)
    d = read_bag(bag, "/odom", "/gps/fix", "/imu")
    t, xyz, q = read_tum(run_dir / "odometry.tum")
    gps = read_gps_csv(run_dir / "gps.csv")
    assert np.allclose(d.t_s, t, atol=1e-9, rtol=0)
    assert np.allclose(d.poses, tum_to_matrices(xyz, q), atol=1e-12, rtol=0)
    assert np.allclose(d.gps.lat_deg, gps.lat_deg, atol=0, rtol=0) and np.allclose(d.gps.sigma_m, gps.sigma_m)
    assert len(d.imu[0]) == len(read_imu_csv(run_dir / "imu.csv")[0]) and not d.camera_frame


@pytest.mark.parametrize("kind", list(BagKind), ids=lambda k: k.value)
def test_fusing_the_bag_gives_the_run_directorys_estimate(run_dir, tmp_path, kind, capsys):
    bag = _bag_of(run_dir, tmp_path / ("b.bag" if kind is BagKind.ros1 else "b"), kind)
    from_files, from_bag = tmp_path / "files.tum", tmp_path / "bag.tum"
    assert main(["fuse", "--map", "grid", "--odometry", str(run_dir / "odometry.tum"), "--gps",
                 str(run_dir / "gps.csv"), "--out", str(from_files)]) == 0
    assert main(["fuse", "--map", "grid", "--bag", str(bag), "--odometry-topic", "/odom", "--gps-topic", "/gps/fix",
                 "--imu-topic", "/imu", "--out", str(from_bag)]) == 0
    ta, xa, qa = read_tum(from_files)
    tb, xb, qb = read_tum(from_bag)
    assert len(ta) > 1000 and np.array_equal(ta, tb)
    assert np.max(np.abs(xa - xb)) <= 1e-9  # both written to 0.1 mm: equal unless an estimate moved
    assert np.max(np.abs(np.abs(qa) - np.abs(qb))) <= 1e-9


def test_an_optical_child_frame_is_read_as_camera_axes(run_dir, tmp_path):
    from mapfusion.replay import body_to_camera

    t, xyz, q = read_tum(run_dir / "odometry.tum")
    body = tum_to_matrices(xyz, q)
    bag = write_bag(tmp_path / "cam", BagKind.mcap, (t, body_to_camera(body)), child_frame="camera_optical_frame")
    d = read_bag(bag, "/odom")
    assert d.camera_frame and np.allclose(d.poses, body, atol=1e-9)


def test_the_out_bag_replays_with_the_right_types_and_frames(run_dir, tmp_path):
    from rosbags.highlevel import AnyReader

    out = tmp_path / "est"
    assert main(["fuse", "--map", "grid", "--odometry", str(run_dir / "odometry.tum"), "--gps",
                 str(run_dir / "gps.csv"), "--out", str(tmp_path / "e.tum"), "--out-bag", str(out)]) == 0
    with AnyReader([out]) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        assert types == {"/mapfusion/odometry": "nav_msgs/msg/Odometry",
                         "/mapfusion/map_priors": "visualization_msgs/msg/MarkerArray"}
        conn = next(c for c in r.connections if c.topic == "/mapfusion/odometry")
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=[conn])]
    t, xyz, _ = read_tum(tmp_path / "e.tum")
    assert len(msgs) == len(t)
    assert {m.header.frame_id for m in msgs} == {"map"} and {m.child_frame_id for m in msgs} == {"base_link"}
    assert abs(msgs[-1].pose.pose.position.x - xyz[-1, 0]) < 1e-4
    assert max(m.pose.covariance[0] for m in msgs) > 0  # the marginals' σ²


@pytest.mark.parametrize("case,needle", [
    ("truncated", "cannot read the bag"),
    ("wrong-type", "is sensor_msgs/msg/NavSatFix"),
    ("no-gps-topic", "/gps/none is not in the bag"),
    ("missing", "no such bag"),
])
def test_a_bad_bag_is_one_line_and_exit_2(run_dir, tmp_path, capsys, case, needle):
    bag = _bag_of(run_dir, tmp_path / "b.bag", BagKind.ros1)
    odo_topic, gps_topic = "/odom", "/gps/fix"
    if case == "truncated":
        bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 3])
    elif case == "wrong-type":
        odo_topic = "/gps/fix"
    elif case == "no-gps-topic":
        gps_topic = "/gps/none"
    elif case == "missing":
        bag = tmp_path / "none.bag"
    code = main(["fuse", "--map", "grid", "--bag", str(bag), "--odometry-topic", odo_topic, "--gps-topic", gps_topic,
                 "--out", str(tmp_path / "e.tum")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "e.tum").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["run_bag", "run.bag"])
def test_the_readmes_bag_example_end_to_end(run_dir, tmp_path, name):
    """export --bag, then fuse --bag with --out-bag: the README's commands, on a simulated run."""
    bag = tmp_path / name
    assert main(["export", str(run_dir), "--bag", str(bag)]) == 0
    assert main(["fuse", "--map", "grid", "--bag", str(bag), "--odometry-topic", "/odom", "--gps-topic", "/gps/fix",
                 "--imu-topic", "/imu", "--out", str(tmp_path / "est.tum"), "--out-bag", str(tmp_path / "est_bag")]) == 0
    assert main(["fuse", "--map", "grid", "--odometry", str(run_dir / "odometry.tum"), "--gps",
                 str(run_dir / "gps.csv"), "--out", str(tmp_path / "files.tum")]) == 0
    _, xa, _ = read_tum(tmp_path / "files.tum")
    _, xb, _ = read_tum(tmp_path / "est.tum")
    assert np.max(np.abs(xa - xb)) <= 1e-9
    assert read_bag(tmp_path / "est_bag", "/mapfusion/odometry").t_s.size == len(xb)


def test_a_wheel_speed_topic_becomes_wheel_csv(run_dir, tmp_path):
    t, xyz, q = read_tum(run_dir / "odometry.tum")
    speed = np.linspace(0.0, 12.5, len(t))
    bag = write_bag(tmp_path / "w", BagKind.sqlite3, (t, tum_to_matrices(xyz, q)), wheel=(t, speed))
    assert main(["import", "bag", "--bag", str(bag), "--odometry-topic", "/odom", "--wheel-topic", "/wheel_speed",
                 "--out", str(tmp_path / "r")]) == 0
    rows = (tmp_path / "r" / "wheel.csv").read_text().splitlines()
    assert rows[0] == "t,speed_mps" and len(rows) == len(t) + 1
    assert abs(float(rows[-1].split(",")[1]) - 12.5) < 1e-4


@pytest.mark.slow
def test_a_bags_wheel_and_imu_topics_are_fused_as_the_files_are(run_dir, tmp_path, capsys):
    """Issue 18: `fuse --bag --wheel-topic --imu-topic` gives the estimate of `fuse --wheel --imu` on the
    same samples, and both use them (the summary's wheel + gyro line)."""
    from mapfusion.formats import read_wheel_csv, write_wheel_csv

    tt, xt, _ = read_tum(run_dir / "truth.tum")
    speed = np.append(np.hypot(*np.diff(xt[:, :2], axis=0).T) / np.diff(tt), 0.0)
    write_wheel_csv(tmp_path / "wheel.csv", tt, speed)
    wheel = read_wheel_csv(tmp_path / "wheel.csv")  # the bag gets the file's very numbers
    t, xyz, q = read_tum(run_dir / "odometry.tum")
    bag = write_bag(tmp_path / "b", BagKind.sqlite3, (t, tum_to_matrices(xyz, q)), read_gps_csv(run_dir / "gps.csv"),
                    read_imu_csv(run_dir / "imu.csv"), wheel=wheel)
    from_files, from_bag = tmp_path / "files.tum", tmp_path / "bag.tum"
    assert main(["fuse", "--map", "grid", "--odometry", str(run_dir / "odometry.tum"), "--gps",
                 str(run_dir / "gps.csv"), "--wheel", str(tmp_path / "wheel.csv"), "--imu", str(run_dir / "imu.csv"),
                 "--out", str(from_files)]) == 0
    assert "wheel + gyro" in capsys.readouterr().out
    assert main(["fuse", "--map", "grid", "--bag", str(bag), "--odometry-topic", "/odom", "--gps-topic", "/gps/fix",
                 "--imu-topic", "/imu", "--wheel-topic", "/wheel_speed", "--out", str(from_bag)]) == 0
    assert "wheel + gyro" in capsys.readouterr().out
    ta, xa, _ = read_tum(from_files)
    tb, xb, _ = read_tum(from_bag)
    assert len(ta) > 1000 and np.array_equal(ta, tb)
    assert np.max(np.abs(xa - xb)) <= 1e-9


def test_the_odometrys_covariance_sets_its_sigma_per_metre(run_dir, tmp_path, capsys):
    from mapfusion.bags import sigma_per_m_from_covariance

    t, xyz, q = read_tum(run_dir / "odometry.tum")
    poses = tum_to_matrices(xyz, q)
    steps = np.hypot(*np.diff(xyz[:, :2], axis=0).T)
    s = 0.03  # σ of a step per metre of it: its variance grows by s² · mean step per metre driven
    var = np.concatenate(([0.0], np.cumsum(s * s * steps * steps[steps > 0].mean())))
    cov = np.zeros((len(t), 6, 6))
    cov[:, 0, 0] = cov[:, 1, 1] = var
    assert abs(sigma_per_m_from_covariance(poses, var) - s) < 1e-3
    bag = write_bag(tmp_path / "c", BagKind.mcap, (t, poses), read_gps_csv(run_dir / "gps.csv"), covariances=cov)
    args = ["fuse", "--map", "grid", "--bag", str(bag), "--odometry-topic", "/odom", "--gps-topic", "/gps/fix"]
    assert main([*args, "--out", str(tmp_path / "a.tum")]) == 0
    err = capsys.readouterr().err
    assert "odometry_sigma_per_m = 0.03" in err
    assert main([*args, "--no-bag-covariance", "--out", str(tmp_path / "b.tum")]) == 0
    assert "odometry_sigma_per_m" not in capsys.readouterr().err
    assert not np.array_equal(read_tum(tmp_path / "a.tum")[1], read_tum(tmp_path / "b.tum")[1])
