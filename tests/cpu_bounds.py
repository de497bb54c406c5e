"""How far the simulator's output may move between CPUs (see tests/sensorbox/test_fixtures.py).

Measured between the AMD EPYC that made the fixtures and an Intel Xeon: LiDAR
points 7.6 um, raw pixels and reflectivities one level, JPEG pixels up to 14
levels in 0.1 % of values (mean 0.0084 levels).
"""

XYZ_TOLERANCE_M = 2e-5  # a few float32 steps at the fixtures' longest ranges
RAW_PIXEL_LEVELS = 1  # raw pixels and point reflectivities
JPEG_MEAN_LEVELS = 0.05  # mean |difference| over all values
JPEG_OFF_BY_3_SHARE = 0.005  # values off by more than 2 levels
