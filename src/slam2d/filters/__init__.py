"""Recursive estimators: dead reckoning, EKF-SLAM, FastSLAM (pure kernels plus thin stateful shells)."""

from slam2d.filters.dead_reckoning import DeadReckoning as DeadReckoning
from slam2d.filters.dead_reckoning import DeadReckoningConfig as DeadReckoningConfig
from slam2d.filters.dead_reckoning import dead_reckoning_step as dead_reckoning_step
