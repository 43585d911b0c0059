"""The consumer GNSS receiver the evaluation simulates (the deployment protocol's fixes, a unit's earlier drives):
10 Hz fixes, position noise per axis, heading only while moving (docs/deviations.md)."""

GNSS_RATE_HZ = 10.0
GNSS_POS_STD_M = 1.5
GNSS_HEADING_STD_DEG = 2.0
GNSS_HEADING_MIN_SPEED_MPS = 2.0
