"""mapfusion bench: every benchmark line carries the anchor measured in the same run and its ratio."""

from __future__ import annotations

import math

from mapfusion.harness.bench import run_benchmarks


def test_bench_lines_carry_their_anchors_and_ratios():
    rows = {r["benchmark"]: r for r in run_benchmarks(duration_s=300.0, city_km=(2.0, 2.0))}
    assert set(rows) == {"roadmap_build", "engine", "engine_hmm", "matcher"}
    eng, hmm = rows["engine"], rows["engine_hmm"]
    assert eng["map_priors"] > 0  # the drive exercises the map
    assert math.isclose(eng["ratio_to_bare"], eng["frames_per_s"] / eng["bare_chain_frames_per_s"])
    assert math.isclose(hmm["ratio_to_single_frame"], hmm["frames_per_s"] / eng["frames_per_s"])
    assert math.isclose(hmm["ratio_to_bare"], hmm["frames_per_s"] / eng["bare_chain_frames_per_s"])
    m = rows["matcher"]
    assert math.isclose(m["single_ratio_to_kdtree"], m["single_matches_per_s"] / m["kdtree_queries_per_s"])
