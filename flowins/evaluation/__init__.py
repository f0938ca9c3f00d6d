"""Evaluation of estimated trajectories: alignment, error metrics, TUM files, plots.

Knows nothing of how a track was made: every function takes plain tensors of
times (s), positions (m) and quaternions (w, x, y, z).
"""
from flowins.evaluation.alignment import (
    Alignment,
    align_yaw,
    apply_alignment,
    apply_alignment_to_quaternions,
    identity_alignment,
    umeyama,
)
from flowins.evaluation.metrics import (
    Association,
    SegmentErrors,
    TrajectoryErrors,
    associate,
    interpolate_positions,
    interpolate_quaternions,
    position_rmse,
    segment_errors,
    trajectory_errors,
)
from flowins.evaluation.plots import plot_errors, plot_trajectory
from flowins.evaluation.tum import read_tum, write_tum

__all__ = [
    "Alignment",
    "Association",
    "SegmentErrors",
    "TrajectoryErrors",
    "align_yaw",
    "apply_alignment",
    "apply_alignment_to_quaternions",
    "associate",
    "identity_alignment",
    "interpolate_positions",
    "interpolate_quaternions",
    "plot_errors",
    "plot_trajectory",
    "position_rmse",
    "read_tum",
    "segment_errors",
    "trajectory_errors",
    "umeyama",
    "write_tum",
]
