"""What the engine did, counted: for ``metrics.json``, ``fusion_events.json`` and diagnostics."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Counters:
    """Event counts of one engine run."""

    frames: int = 0
    odometry_rejected: int = 0
    odometry_jumps: int = 0  # steps implying an impossible speed: bridged, never followed (issue 19)
    gps_used: int = 0
    gps_rejected_gate: int = 0
    gps_rejected_invalid: int = 0  # non-finite, or latitude/longitude out of range
    gps_rejected_time: int = 0  # no odometry frame near its time (before the first, after the last, in a gap)
    gps_before_init: int = 0
    map_priors: int = 0
    priors_gated: int = 0
    matches: int = 0
    odometry_priors: int = 0
    recoveries: int = 0
    gps_relocalisations: int = 0
    gps_rescales: int = 0  # re-localisations by a track run that also re-scaled the odometry (issue 16)
    updates: int = 0
    lost_events: int = 0  # road hypotheses: the estimate lost (issue 16)
    odometry_vetoed: int = 0  # odometry steps that disagreed with wheel + gyro: replaced by theirs (issue 18)
    map_relocalisations: int = 0  # the vehicle found on the road network without GPS (issue 17)
    heading_priors: int = 0  # yaw-only priors from a straight road the estimate is on (heading_prior_sigma_deg)
    road_fixes: int = 0  # the road particles' positions added as fixes while GPS was silent (road_fixes)
    road_fixes_gated: int = 0  # and confident answers not added: not moved as the estimate did (the gate)
    wheel_frames: int = 0  # frames wheel + gyro made alone, the odometry silent (issue 18)

    @property
    def gps_rejected(self) -> int:
        """Fixes not used, for any reason."""
        return self.gps_rejected_gate + self.gps_rejected_invalid + self.gps_rejected_time

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)
