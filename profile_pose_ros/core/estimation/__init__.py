"""Profile -> pose (estimator.estimate_pose): corner detection, closed form, refinement, checks.

Read bottom-up: corners, dense, residuals and result (types, reasons, the residual algebra in numpy),
stages (each stage on the compiled kernels), hidden_face (a face a gap hides), estimator (the whole
estimate in one compiled call, compiled/profile_kernel.py)."""
