"""Simulated odometry that fails like real odometry (issue 22).

The ``vo`` preset is fitted to the real stereo VO results (CVO) and ``mono`` to the real monocular
ones (TrianFlow) in ``$MAPFUSION_DATA/vo/``, on the five KITTI drives. Here, per drive: KITTI's
t_err and r_err of the simulated odometry (four seeds, on the drive's own truth) lie within the range
the real results span, ± 30%; rain is at least 1.5× clear; and Map-Fusion's verdict (better or worse
than without the map) on the simulated odometry (the ``kitti-realism`` family) agrees with its verdict
on the real output of the same drive (``kitti-real``) on at least 80% of the (drive, method) pairs.
The table of both is printed at the end of ``pytest scenarios/``.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapfusion.harness.realism import format_stats, real_stats, simulated_stats, verdict_pairs, within_real_range

from .conftest import REPORTS, family_group, family_results, real_data

pytestmark = [pytest.mark.sumo, pytest.mark.slow]  # minutes of drives: pytest -m slow (CI)

PRESETS = ("vo", "mono")


@pytest.fixture(scope="module")
def data():
    return real_data("vo", "the realism checks need the real VO results")


@pytest.fixture(scope="module")
def stats(data):
    out = {(p, "real"): real_stats(data, p) for p in PRESETS}
    for p in PRESETS:
        for weather in ("clear", "rain"):
            out[(p, weather)] = simulated_stats(data, p, weather)
    lines = []
    for p in PRESETS:
        lines += [f"{p}: the real output it is fitted on, then the preset in clear weather and in rain "
                  f"(mean of seeds 1–4 on the drive's truth)"]
        lines += format_stats(out[(p, "real")] + out[(p, "clear")] + out[(p, "rain")]) + [""]
    REPORTS["realism: simulated odometry beside the real outputs (issue 22)"] = lines
    return out


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.parametrize("field", ["t_err_percent", "r_err_deg_per_100m"])
def test_clear_within_the_real_range(stats, preset, field):
    outside = within_real_range(stats[(preset, "clear")], stats[(preset, "real")], field)
    assert not outside, outside


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.parametrize("field", ["t_err_percent", "r_err_deg_per_100m"])
def test_rain_at_least_one_and_a_half_times_clear(stats, preset, field):
    clear = np.mean([getattr(r, field) for r in stats[(preset, "clear")]])
    rain = np.mean([getattr(r, field) for r in stats[(preset, "rain")]])
    assert rain >= 1.5 * clear, f"{preset} {field}: rain {rain:.3g} < 1.5 × clear {clear:.3g}"


@pytest.mark.xdist_group(family_group("kitti-realism"))  # (on the worker that runs both families)
def test_map_fusion_verdict_agrees_with_the_real_outputs(request, data):
    cfg = request.config
    sim_rows, real_rows = family_results(cfg, "kitti-realism").values(), family_results(cfg, "kitti-real").values()
    pairs = verdict_pairs(list(sim_rows), list(real_rows))
    lines = [f"{'drive':>5} {'preset':>6} {'simulated':>10} {'real':>7}"]
    lines += [f"{d:>5} {p:>6} {s or 'failed':>10} {r or 'failed':>7}" for d, p, s, r in pairs]
    agree = sum(1 for _, _, s, r in pairs if s is not None and s == r)
    lines.append(f"agree on {agree} of {len(pairs)}")
    REPORTS["realism: Map-Fusion's verdict on simulated and on real odometry, same drives (issue 22)"] = lines
    assert agree >= 0.8 * len(pairs), "\n".join(lines)
