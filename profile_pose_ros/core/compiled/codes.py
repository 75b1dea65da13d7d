"""Status codes, the option-vector layout and the refinement's stopping rules of the compiled estimator,
shared with the Python that calls it.

Kept apart from the kernels so that code using a prebuilt kernel never imports numba.
"""

# status codes (the Python wrapper turns them into reasons)
OK = 0
TOO_FEW_POINTS = 2
X_NOT_INCREASING = 3
STEEP_SEGMENT = 4
WRONG_CORNER_COUNT = 5
CORNER_NOT_BETWEEN = 6
CORNERS_NOT_INCREASING = 7
CF_RANK = 8
CF_DEGENERATE = 9
NOT_FINITE = 11
REPROJECTION = 12
OUTSIDE_FOOTPRINT = 13
SINGULAR = 14
INCONSISTENT = 15  # the corners' residuals are far beyond what the profile's own noise explains
AMBIGUOUS = 16  # four ridges: another minimum far from the best fits the corners about as well
NO_START = 17  # four ridges: the rotation constraints have no real solution along the free direction
NO_CONVERGED = 18  # four ridges: no starting pose's refinement converged
# added to a status when the dense refinement's solution (not the corners') failed: SINGULAR or a check
DENSE_STAGE = 64

# two minima are rivals when the other's cost (chi-square) is this close to the best's and it lies this many
# standard deviations (Mahalanobis, under the best minimum's covariance) away: the lower cost is a coin toss
AMBIGUOUS_COST = 9.0
AMBIGUOUS_DISTANCE = 5.0

# decode_xz statuses (its count says how many points)
DECODED, OFF_PLANE, ALL_INVALID = 0, 1, 2

# partial views (partial_kernel.py, profile_kernel.py, estimation/hidden_face.py)
GAP_PITCHES = 3.0  # a run between two valid points wider than this many point pitches is a gap, not the spacing
MIN_RIDGES = 4  # the fewest the estimator solves (model.gauge.MIN_RIDGES): a gauge seen in part must keep as many
# the most adjacent faces one gap may hide: two narrow faces side by side under a gap over their corner
MAX_HIDDEN_IN_A_GAP = 2
# whose estimate profile_kernel.estimate returns (which[0]): the whole gauge's, or which hypothesis decided ...
PARTIAL_NONE, PARTIAL_HIDDEN, PARTIAL_IN_VIEW, PARTIAL_AMBIGUOUS = 0, 1, 2, 3
# ... and, for faces a gap hides, what became of its pose (which[3])
VERDICT_ACCEPTED, VERDICT_PARALLEL, VERDICT_REFUSED, VERDICT_IMPRECISE, VERDICT_OUTSIDE, VERDICT_WHERE_POINTS = range(6)

# option vector layout
O_EPS, O_TRIM, O_MINSEG, O_MINANGLE, O_MAXFACE, O_MAXOFF, O_ROBUST, O_THR, O_FLOOR, O_NOISE, O_SIGFLOOR, \
    O_WEIGHTED, O_REFINE, O_MAXIT, O_MAXREPROJ, O_MARGIN, O_PASSES, O_SPIKE, O_MAXRATIO, O_GAP, O_SEARCH, \
    O_SEARCHSIG, O_DENSE, O_DMARGIN, O_DTHR, O_DFLOOR, O_DITER, O_DENSESIG = range(28)
N_OPTIONS = 28
DENSE_NEVER, DENSE_ALWAYS, DENSE_WHEN_POORLY_DETERMINED = 0, 1, 2  # O_DENSE: refine_model corners, dense, auto

JIT = dict(cache=True, error_model="numpy", nogil=True)  # numba.njit options of every compiled function

# the longest glint (points side by side) the glint filter drops whole (estimate_kernel._drop_spikes); a longer
# run is wider than a glint lights and is left to the segments (shorter than a face, it is debris there)
MAX_GLINT_RUN = 16

# the refinement's final Gauss-Newton polish
POLISH_STEPS = 4
POLISH_COST_TOLERANCE = 1e-9
POLISH_STEP_TOLERANCE = 1e-12  # m or rad: the next Gauss-Newton step would be far below this
# the weights formed again at the minimum (estimate_kernel._refine) until a step under them would move the pose
# by less than this (chi-square: a tenth of its standard deviation), at most this many times in all
REWEIGHT_CHI2 = 1e-2
REWEIGHT_ROUNDS = 10
# ... but not at a minimum whose residuals are over a hundred times what the corners' noise explains (chi-square
# per residual): a wrong placement of a partial view, or the wrong gauge. Weights turning by a fraction of a
# standard deviation cannot make such a fit consistent; the checks refuse it at any max_residual_ratio below
# 100 (above, it is kept as weighted so far). Its further rounds were most of a gap profile's slow tail
REWEIGHT_HOPELESS_CHI2 = 1e4
# the published covariance is the estimate's times this: its errors have a slightly heavier tail than a Gaussian
# (spikes the robust cuts keep, the cost valley's bend), so the linearised covariance, honest in the mean, puts
# about a quarter too many poses beyond chi-square's 99 % point; scaled, that share is the 1 % it claims
# (docs/estimator.md, "Covariance calibration"). The estimator's own decisions use the unscaled covariance.
COVARIANCE_CALIBRATION = 1.05
