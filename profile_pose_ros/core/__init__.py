"""Pure computation for profile_pose_ros: numpy/scipy only, never rclpy.

    from profile_pose_ros.core import Gauge, render_profile, estimate_pose
"""
from .corners import CornerOptions, CornerResult, detect_corners
from .estimator import EstimatorOptions, PoseEstimate, estimate_pose, pose_error
from .gauge import Gauge, GaugeError
from .poses import PoseRange, corners_visible, sample_pose
from .render import DEFAULT_PROFILER, ProfilerModel, render_profile, true_corners
from .solver import PoseSolution, closed_form

__all__ = [
    "CornerOptions", "CornerResult", "DEFAULT_PROFILER", "EstimatorOptions", "Gauge", "GaugeError",
    "PoseEstimate", "PoseRange", "PoseSolution", "ProfilerModel", "closed_form", "corners_visible",
    "detect_corners", "estimate_pose", "pose_error", "render_profile", "sample_pose", "true_corners",
]
