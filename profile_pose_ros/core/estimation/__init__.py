"""Profile -> pose (estimator.estimate_pose): corner detection, closed form, refinement, checks.

Read bottom-up: corners, dense, solver and result (types, reasons, the closed forms and residual algebra),
stages (each stage on the compiled kernels), pipeline (several starts and the basin search), estimator
(one compiled call for the common case, the pipeline for the rest)."""
