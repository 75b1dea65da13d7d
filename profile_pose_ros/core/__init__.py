"""Pure computation for profile_pose_ros: never rclpy. numpy and scipy throughout; numba only in compiled/.

Rooms, each importing only those listed before it:
    model       the gauge, rotations, poses, rendering a profile
    timing      clock maps and stamp freshness (standalone)
    compiled    numba kernels and the loader that picks their build
    wire        CDR and device protocols (decoding a profile uses compiled.loader)
    estimation  profile -> pose
    control     compensators, limits, safety
    design      gauge design and bounds
    commissioning  where the gauge and the profiler sit (hand-eye), the first-motion check

    from profile_pose_ros.core import Gauge, render_profile, estimate_pose
"""
from .estimation.corners import CornerOptions, CornerResult
from .estimation.estimator import estimate_pose, pose_error, warm_up
from .estimation.result import EstimatorOptions, PoseEstimate
from .estimation.residuals import PoseSolution
from .estimation.stages import detect_corners
from .model.gauge import Gauge, GaugeError
from .model.poses import PoseRange, corners_visible, sample_pose
from .model.render import DEFAULT_PROFILER, ProfilerModel, render_profile, true_corners

__all__ = [
    "CornerOptions", "CornerResult", "DEFAULT_PROFILER", "EstimatorOptions", "Gauge", "GaugeError",
    "PoseEstimate", "PoseRange", "PoseSolution", "ProfilerModel", "corners_visible",
    "detect_corners", "estimate_pose", "pose_error", "render_profile", "sample_pose", "true_corners", "warm_up",
]
