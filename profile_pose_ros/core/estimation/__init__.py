"""Profile -> pose: corner detection, closed form, refinement, checks (estimator.estimate_pose), on the
compiled kernels (compiled_path) or the numpy reference (plain)."""
