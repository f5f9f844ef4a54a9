"""Evaluation metrics (numpy/scipy only)."""

from slam2d.eval.trajectory import ATEResult as ATEResult
from slam2d.eval.trajectory import RPEResult as RPEResult
from slam2d.eval.trajectory import align_se2 as align_se2
from slam2d.eval.trajectory import ate as ate
from slam2d.eval.trajectory import rpe as rpe
