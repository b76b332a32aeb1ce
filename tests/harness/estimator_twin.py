"""The external form of tests/harness/test_estimators.py's GpsDeadReckoning: reads the run's inputs as files
(``estimator_twin.py ODOMETRY.tum GPS.csv MAP OUT.tum``), feeds the same class in the same order, writes its
estimates as TUM at full precision. ``--fail`` exits 3 with a message instead."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # (run from a temporary folder: the checkout)

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402


def main(argv: list[str]) -> int:
    if argv[0] == "--fail":
        print("the twin was told to fail", file=sys.stderr)
        return 3
    odometry, gps, map_path, out = argv
    from mapfusion import RoadMap
    from tests.harness.test_estimators import GpsDeadReckoning

    odo = np.loadtxt(odometry, comments="#", ndmin=2)
    fixes = np.genfromtxt(gps, delimiter=",", names=True, ndmin=1)
    poses = np.tile(np.eye(4), (len(odo), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(odo[:, 4:8]).as_matrix()
    poses[:, :3, 3] = odo[:, 1:4]
    est = GpsDeadReckoning(RoadMap.from_osm(map_path))
    events = sorted([(float(t), 2, i) for i, t in enumerate(fixes["t"])] +
                    [(float(t), 3, i) for i, t in enumerate(odo[:, 0])])
    lines = []
    for t, kind, i in events:
        if kind == 2:
            est.add_gps(t, float(fixes["lat"][i]), float(fixes["lon"][i]))
        elif i > 0:
            est.add_odometry(t, np.linalg.solve(poses[i - 1], poses[i]))
            p = est.estimate()
            if p is not None:
                q = Rotation.from_matrix(p[:3, :3]).as_quat()
                lines.append(" ".join(repr(float(v)) for v in (t, *p[:3, 3], *q)))
    Path(out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
