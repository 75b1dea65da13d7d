"""Where the gauge and the profiler sit: robot-world / hand-eye calibration from static stations.

At each station the arm holds still; the controller reports its tool's pose in the base frame (A_i) and
the estimator the profiler's pose in the gauge frame (M_i, with its covariance). With X the profiler on the
tool (the mount) and Y the gauge in the base frame, every station says

    A_i X = Y M_i

and one weighted least squares over all stations finds X and Y (12 unknowns), started from the closed
form of the relative motions (A'X = XB', Park and Martin), each station weighted by its pose covariance
plus the robot's own pose noise. The covariance of X and Y comes from the same linearisation. A sequence
is refused, with the reason, when it cannot determine X and Y (too few rotation axes, a standard deviation
over its bound) or when the residuals are not what the covariances predict (a chi-square test: a gauge
that moved, a robot that slipped, a pose that was wrong): a calibration must never be quietly wrong.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from ..model.rotation import so3_exp, so3_log
from ..model.transform import Transform, difference

# The unknowns' order: X = profiler in tool (translation, rotation), then Y = gauge in base
X_TRANSLATION, X_ROTATION, Y_TRANSLATION, Y_ROTATION = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
MIN_TURN = 5e-4  # rad: a relative move turning less than this tells the closed form nothing about rotation axes


@dataclass(frozen=True)
class Station:
    tool_in_base: Transform  # A_i, as the controller reports it
    profiler_in_gauge: Transform  # M_i, the estimate (averaged over the station's poses)
    covariance: np.ndarray  # 6x6 of M_i, ROS order (x y z in G, then a small rotation in G: R = exp(d) R_est)
    poses: int = 1  # how many estimates the station averages (for the report)


@dataclass(frozen=True)
class Bounds:
    """What a calibration must reach to be used (standard deviations), how unlikely its residuals may be, and
    the noise of the controller's reported pose it assumes."""

    rotation_sigma: float = 1e-3  # rad, each axis of either rotation
    translation_sigma: float = 1e-4  # m, each axis of the profiler's place on the tool
    min_p_value: float = 1e-3  # chi-square test of the residuals against the covariances
    robot_translation_sigma: float = 5e-6  # m, the controller's reported pose: its repeatability
    robot_rotation_sigma: float = 1e-5  # rad


@dataclass
class Calibration:
    profiler_in_tool: Transform  # X
    gauge_in_base: Transform  # Y
    covariance: np.ndarray  # 12x12: X translation (in the tool frame), X rotation (left, tool frame), Y likewise
    chi2: float
    dof: int
    p_value: float
    station_chi2: np.ndarray  # per station (6 dof each)
    station_residuals: np.ndarray  # per station: x y z (m) and rotation vector (rad) in G, measured - predicted
    refused: str | None = None  # why this calibration must not be used; None: it may

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def mean_transform(transforms: list[Transform]) -> Transform:
    """The average of nearby transforms (rotations averaged as small turns about the first)."""
    first = transforms[0].rotation
    turn = np.mean([so3_log(t.rotation @ first.T) for t in transforms], axis=0)
    return Transform(so3_exp(turn) @ first, np.mean([t.translation for t in transforms], axis=0))


def station(tool_poses: list[Transform], estimates: list[Transform], covariances: list[np.ndarray]) -> Station:
    """One station from what was recorded while the arm held still: the controller's poses averaged, the
    estimates averaged, their covariance that of a mean of independent estimates."""
    covariance = np.mean(covariances, axis=0) / len(estimates)
    return Station(mean_transform(tool_poses), mean_transform(estimates), covariance, len(estimates))


class CalibrationError(ValueError):
    """The stations cannot give a calibration at all (too few, or no two rotation axes)."""


def solve(stations: list[Station], bounds: Bounds = Bounds()) -> Calibration:
    if len(stations) < 3:
        raise CalibrationError(f"{len(stations)} stations: at least 3 (two turns about different axes) are needed")
    x0 = _closed_form_mount(stations)
    y0 = _mean_gauge(stations, x0)
    weights = [_whitening(s, x0, bounds) for s in stations]

    def residuals(p: np.ndarray) -> np.ndarray:
        x, y = _perturbed(x0, p[:6]), _perturbed(y0, p[6:])
        return np.concatenate([w @ _residual(s, x, y) for s, w in zip(stations, weights)])

    fit = optimize.least_squares(residuals, np.zeros(12), method="lm", x_scale=1e-3)  # mm and mrad corrections
    x, y = _perturbed(x0, fit.x[:6]), _perturbed(y0, fit.x[6:])
    information = fit.jac.T @ fit.jac
    if np.linalg.cond(information) > 1e14:
        raise CalibrationError("the moves do not determine the mount and the gauge's place (a singular system): "
                               "turn about at least two different axes")
    covariance = np.linalg.inv(information)
    whitened = fit.fun.reshape(len(stations), 6)
    station_chi2 = np.einsum("ij,ij->i", whitened, whitened)
    chi2 = float(station_chi2.sum())
    dof = 6 * len(stations) - 12
    p_value = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    result = Calibration(x, y, covariance, chi2, dof, p_value, station_chi2,
                         np.array([_residual(s, x, y) for s in stations]))
    result.refused = _refusal(result, bounds)
    return result


def _perturbed(base: Transform, p: np.ndarray) -> Transform:
    """base moved by p: translation added, rotation turned by exp(p[3:]) in the parent frame."""
    return Transform(so3_exp(p[3:]) @ base.rotation, base.translation + p[:3])


def _residual(station: Station, x: Transform, y: Transform) -> np.ndarray:
    """The estimate minus what X and Y predict for it, in the estimate's own terms (G frame)."""
    return difference(station.profiler_in_gauge, y.inverse() @ station.tool_in_base @ x)


def _whitening(station: Station, x: Transform, bounds: Bounds) -> np.ndarray:
    """W with W^T W the inverse of the station's residual covariance: the estimate's, plus the robot's pose
    noise carried to the profiler (a turn of the tool moves the profiler by the lever arm too)."""
    lever = float(np.linalg.norm(x.translation))
    robot = np.diag([bounds.robot_translation_sigma ** 2 + (bounds.robot_rotation_sigma * lever) ** 2] * 3
                    + [bounds.robot_rotation_sigma ** 2] * 3)
    return np.linalg.inv(np.linalg.cholesky(station.covariance + robot))


def _closed_form_mount(stations: list[Station]) -> Transform:
    """X from the motions relative to the first station: A'X = XB' gives log(R_A') = R_X log(R_B') for the
    rotations, then (R_A' - I) t_X = R_X t_B' - t_A' for the translation (linear least squares)."""
    first = stations[0]
    moves = [(first.tool_in_base.inverse() @ s.tool_in_base, first.profiler_in_gauge.inverse() @ s.profiler_in_gauge)
             for s in stations[1:]]
    turns = [(so3_log(a.rotation), so3_log(b.rotation)) for a, b in moves if np.linalg.norm(so3_log(a.rotation)) > MIN_TURN]
    axes = np.array([a / np.linalg.norm(a) for a, _ in turns]) if turns else np.zeros((0, 3))
    if len(turns) < 2 or np.linalg.matrix_rank(axes, tol=0.1) < 2:
        raise CalibrationError("the moves turn the tool about fewer than two different axes: the profiler's "
                               "orientation on the tool is not determined")
    robot_axes, profiler_axes = np.array([a for a, _ in turns]), np.array([b for _, b in turns])
    u, _, vt = np.linalg.svd(robot_axes.T @ profiler_axes)
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    lhs = np.vstack([a.rotation - np.eye(3) for a, _ in moves])
    rhs = np.concatenate([rotation @ b.translation - a.translation for a, b in moves])
    translation = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return Transform(rotation, translation)


def _mean_gauge(stations: list[Station], x: Transform) -> Transform:
    """Y = A_i X M_i^-1, averaged over the stations."""
    return mean_transform([s.tool_in_base @ x @ s.profiler_in_gauge.inverse() for s in stations])


def _refusal(result: Calibration, bounds: Bounds) -> str | None:
    sigma = result.sigma
    for name, part, bound, unit, scale in (("the profiler's rotation on the tool", X_ROTATION, bounds.rotation_sigma, "mrad", 1e3),
                                           ("the profiler's place on the tool", X_TRANSLATION, bounds.translation_sigma, "mm", 1e3),
                                           ("the gauge's rotation in the base frame", Y_ROTATION, bounds.rotation_sigma, "mrad", 1e3)):
        worst = float(sigma[part].max())
        if worst > bound:
            return (f"badly conditioned: {name} is determined to {worst * scale:.3g} {unit} (std), over the bound "
                    f"{bound * scale:g} {unit}: turn further, or about more axes")
    if result.p_value < bounds.min_p_value:
        worst = int(np.argmax(result.station_chi2))
        r = result.station_residuals[worst]
        return (f"inconsistent: the residuals are not what the pose covariances predict (chi2 {result.chi2:.1f} on "
                f"{result.dof} dof, p = {result.p_value:.2g}); worst at station {worst} ({np.linalg.norm(r[:3]) * 1e6:.1f} "
                f"um, {np.linalg.norm(r[3:]) * 1e3:.3f} mrad): did the gauge move, or the robot slip?")
    return None
