"""The localiser's failure rule (McManus et al. 2015, §4.3), defined once.

A localisation *fails* when the vehicle has travelled more than :data:`FAILURE_DISTANCE_M` (20 m) on
dead reckoning since its last accepted localisation (or oracle reset).  The localiser block applies it
(:meth:`scenesig.localiser.pipeline.Localiser.check_failure`: reset from the oracle, or declare itself lost
without one); the evaluation counts failures with it where no resets were recorded
(:func:`scenesig.localiser.evaluation.coverage_metrics`); its distance is also the one of
``blind_fraction_over_20m``.
"""
from __future__ import annotations

__all__ = ["FAILURE_DISTANCE_M", "is_failure"]

#: McManus et al. 2015, §4.3: more than 20 m travelled blind (dead reckoning only) is a failure.
FAILURE_DISTANCE_M = 20.0

# Slack so that float round-off of summed odometry increments does not declare a failure at exactly
# the limit (20 increments of 1 m sum to 20.000000000000004 on some orders).
_SLACK_M = 1e-9


def is_failure(blind_m: float, failure_distance_m: float = FAILURE_DISTANCE_M) -> bool:
    """True when ``blind_m`` metres on dead reckoning exceed the failure distance.

    Parameters
    ----------
    blind_m : distance (m) travelled since the last localisation or reset.
    failure_distance_m : the limit (the localiser's ``failure_distance_m`` setting).
    """
    if not failure_distance_m > 0:
        raise ValueError(f"failure_distance_m must be > 0, got {failure_distance_m}")
    return float(blind_m) > float(failure_distance_m) + _SLACK_M
