"""mapfusion bench: every benchmark line carries the anchor measured in the same run and its ratio."""

from __future__ import annotations

import math
import tempfile

from mapfusion.config import FusionConfig, RoadTracking
from mapfusion.harness import bench
from mapfusion.harness.bench import run_benchmarks


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def test_bench_lines_carry_their_anchors_and_ratios(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    rows = {r["benchmark"]: r for r in run_benchmarks(duration_s=300.0, city_km=(2.0, 2.0), repeats=3)}
    assert list(tmp_path.iterdir()) == []  # its synthetic city's files are not left behind
    assert set(rows) == {"roadmap_build", "engine", "engine_hmm", "matcher", "relocalise"}
    rel = rows["relocalise"]
    assert rel["particles"] > 0 and math.isclose(rel["realtime_factor"], rel["drive_s"] / rel["compute_s"])
    eng, hmm = rows["engine"], rows["engine_hmm"]
    assert eng["map_priors"] > 0  # the drive exercises the map
    # growth over the drive after its GPS (300 s: 170 s of it) as well as over the whole drive
    assert math.isfinite(eng["growth_after_gps"]) and eng["growth_after_gps"] > 0 and hmm["growth_after_gps"] > 0
    # each round's ratio is to the anchor measured beside it; the line gives their median
    r = eng["rounds"]
    assert len(r["ratio_to_bare"]) == 3
    for fps, bare, ratio in zip(r["frames_per_s"], r["bare_chain_frames_per_s"], r["ratio_to_bare"]):
        assert math.isclose(ratio, fps / bare)
    assert math.isclose(eng["ratio_to_bare"], _median(r["ratio_to_bare"]))
    assert math.isclose(eng["frames_per_s"], _median(r["frames_per_s"]))
    h = hmm["rounds"]
    for fps, bare, ratio in zip(h["frames_per_s"], r["bare_chain_frames_per_s"], h["ratio_to_bare"]):
        assert math.isclose(ratio, fps / bare)
    assert math.isclose(hmm["ratio_to_bare"], _median(h["ratio_to_bare"]))
    # the floor: GTSAM's updates and the road fixes' particles are part of every engine frame's time, so no round's
    # ratio exceeds the bound they leave (a timing that missed them would leave an infinite or a lower bound)
    for line in (eng, hmm):
        rr = line["rounds"]
        assert all(u > 0 for u in rr["gtsam_update_us_per_frame"]) and all(p > 0 for p in rr["road_fixes_us_per_frame"])
        for ratio, bound in zip(rr["ratio_to_bare"], rr["ratio_to_bare_at_most"]):
            assert ratio <= bound
        for bare, u, p, bound in zip(r["bare_chain_frames_per_s"], rr["gtsam_update_us_per_frame"],
                                     rr["road_fixes_us_per_frame"], rr["ratio_to_bare_at_most"]):
            assert math.isclose(bound, 1e6 / bare / (u + p))
        assert math.isclose(line["ratio_to_bare_at_most"], _median(rr["ratio_to_bare_at_most"]))
    m = rows["matcher"]
    ratios = [s / k for s, k in zip(m["rounds"]["single_matches_per_s"], m["rounds"]["kdtree_queries_per_s"])]
    assert math.isclose(m["single_ratio_to_kdtree"], _median(ratios))
    assert 0.0 < m["batch_first_pass_settled"] <= 1.0


def test_the_engine_lines_measure_the_configuration_given(monkeypatch):
    """``mapfusion bench --config``: both engine lines run the configuration given (the road-hypotheses line with
    road_tracking = "hmm" added to it): without road fixes no frame spends time in their particles."""
    seen = []
    real = bench.bench_engine

    def spy(road, **kw):
        seen.append(kw["config"])
        return real(road, **kw)

    monkeypatch.setattr(bench, "bench_engine", spy)
    rows = run_benchmarks(duration_s=150.0, city_km=(1.0, 1.0), repeats=1, config=FusionConfig(road_fixes=False))
    got = {r["benchmark"]: r for r in (next(rows), next(rows), next(rows))}
    assert [c.road_fixes for c in seen] == [False, False]
    assert [c.road_tracking for c in seen] == [FusionConfig().road_tracking, RoadTracking.hmm]
    for line in ("engine", "engine_hmm"):
        assert got[line]["road_fixes_us_per_frame"] == 0.0 and got[line]["gtsam_update_us_per_frame"] > 0
