"""Checking a gauge before it is made (paper III-D): design rules, range of motion, occlusion, precision.

Range of motion (Fig. 4a) is measured, not estimated from margins by hand: from a nominal pose (profiler
straight down, laser line across the gauge centre, gauge mid-height in the middle of the depth range) the
profiler is moved along its x, its z and the gauge's y until a corner is no longer seen with clearance;
the permissible range is the sum of both sides. The incidence limit (Fig. 4b): self-occlusion starts
when the ray's angle from the vertical, alpha, exceeds beta, the smallest angle between a top face and
the vertical (90 deg minus the steepest face); the paper's wording calls beta a maximum, but its rule
("steep planes give a small beta") needs the steepest face. alpha is also found by tilting the profiler
in its laser plane until a corner is lost.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .crlb import corner_crlb, dense_crlb, position_rotation_rms
from ..model.gauge import Gauge
from .gauge_design import RandomGaugeRules, distinct_directions, face_widths
from ..model.poses import LOOKING_DOWN, corners_visible, mid_height
from ..model.render import DEFAULT_PROFILER, ProfilerModel
from ..model.rotation import so3_exp


@dataclass(frozen=True)
class RuleCheck:
    rule: str
    value: float
    limit: float
    ok: bool
    unit: str = ""


def adjacent_face_angles_deg(gauge: Gauge) -> np.ndarray:
    """Angle between each pair of consecutive faces (a corner the profile can see needs a real bend)."""
    cos = np.sum(gauge.normals[1:] * gauge.normals[:-1], axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def profile_bends_deg(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The bend at each corner as the profile shows it at a pose (F in G): the angle between the lines the two
    faces cut in the laser plane, which is what corner detection's min_corner_angle compares. It differs from
    the faces' own angle (adjacent_face_angles_deg) by what the laser plane does not see of it."""
    along_x, along_z = gauge.normals @ rotation[:, 0], gauge.normals @ rotation[:, 2]  # face k: a x + b z = c
    slopes = np.degrees(np.arctan(-along_x / along_z))  # each line's direction in the profile's x-z
    return np.abs(np.diff(slopes))


def _least_over_the_pose_range(gauge: Gauge, measures: tuple, poses: int, seed: int) -> tuple[np.ndarray, ...]:
    """For each measure(gauge, rotation, translation), element by element the least at the nominal pose and over
    poses drawn from the pose range, one draw for all of them (model.poses; none where no pose shows every
    corner, which check_rules reports on its own)."""
    from ..model.poses import sample_pose

    rng = np.random.default_rng(seed)
    drawn = [nominal_pose(gauge)]
    for _ in range(poses):
        try:
            drawn.append(sample_pose(gauge, rng, max_tries=200))
        except RuntimeError:  # the poses drawn so far still count
            break
    return tuple(np.min([measure(gauge, *pose) for pose in drawn], axis=0) for measure in measures)


def profile_face_widths(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Each inner face's (1 .. n - 1) span along the laser line at a pose (m): the points corner detection gets of
    it are this over the profile's pitch. The end faces reach the gauge's edges."""
    from ..model.render import true_corners

    return np.diff(true_corners(gauge, rotation, translation)[:, 0])


def weakest_profile_bends_deg(gauge: Gauge, poses: int = 20, seed: int = 0) -> np.ndarray:
    """Each corner's smallest bend in the profile over the pose range."""
    return _least_over_the_pose_range(gauge, (profile_bends_deg,), poses, seed)[0]


def narrowest_profile_faces(gauge: Gauge, poses: int = 20, seed: int = 0) -> np.ndarray:
    """Each inner face's narrowest span in the profile over the pose range (m)."""
    return _least_over_the_pose_range(gauge, (profile_face_widths,), poses, seed)[0]


def weakest_bends_and_narrowest_faces(gauge: Gauge, poses: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """weakest_profile_bends_deg and narrowest_profile_faces over one draw of the poses (a node needs both at
    start, and drawing them takes tens of ms)."""
    return _least_over_the_pose_range(gauge, (profile_bends_deg, profile_face_widths), poses, seed)


def profile_pitch(points: np.ndarray) -> float:
    """The spacing of a profile's valid points along x (m; the median step, either order), NaN with fewer than
    two."""
    x = points[np.isfinite(points).all(axis=1), 0]
    return float(np.median(np.abs(np.diff(x)))) if x.size > 1 else float("nan")


NARROW_FACE_MARGIN = 1.5  # a face's segment loses points to the corners either side (RDP, the trim, the bend)


def narrow_face_warning(gauge: Gauge, min_segment_points: int, pitch: float,
                        widths: np.ndarray | None = None) -> str | None:
    """Words for a commissioning engineer when some face, in the profiles of the pose range and at this profile
    pitch (m), holds fewer than NARROW_FACE_MARGIN x min_segment_points points: corner detection ignores its
    segment and refuses the profile as a face short, as with a binned or thinned profiler (0.3 mm pitch: random
    seven-ridge gauges refused 47 % instead of 3 %, docs/estimator.md). None when every face holds enough, or the
    pitch is unknown. widths: narrowest_profile_faces(gauge), when the caller keeps it."""
    if not pitch > 0:
        return None
    if widths is None:
        widths = narrowest_profile_faces(gauge)
    points = widths / pitch
    narrow = np.flatnonzero(points < NARROW_FACE_MARGIN * min_segment_points)
    if len(narrow) == 0:
        return None
    faces = ", ".join(f"face {k + 1} as little as {widths[k] * 1e3:.1f} mm, {points[k]:.0f} points" for k in narrow)
    suggested = max(3, int(points[narrow].min() / NARROW_FACE_MARGIN))
    return (f"gauge '{gauge.name}': faces narrow in the profile at its pitch of {pitch * 1e3:.3f} mm ({faces}; corner "
            f"detection ignores segments of fewer than min_segment_points, {min_segment_points}): expect profiles "
            f"refused as 'corner detection: found' fewer than {gauge.n_ridges} corners where they are. A finer "
            f"pitch (less binning or thinning), or min_segment_points near {suggested}, keeps them")


def weak_corner_warning(gauge: Gauge, min_corner_angle: float, bends: np.ndarray | None = None) -> str | None:
    """Words for a commissioning engineer when some corner bends, in the profiles of the pose range, by less than
    twice what corner detection needs (min_corner_angle, rad): under it detection merges the two faces and
    refuses the profile ("found n - 1 corners"), and near it often does. None when every corner bends enough.
    bends: weakest_profile_bends_deg(gauge), when the caller keeps it (drawing the poses takes tens of ms)."""
    if bends is None:
        bends = weakest_profile_bends_deg(gauge)
    needed = np.degrees(min_corner_angle)
    weak = np.flatnonzero(bends < 2 * needed)
    if len(weak) == 0:
        return None
    corners = ", ".join(f"faces {k}/{k + 1} as little as {bends[k]:.1f} deg" for k in weak)
    return (f"gauge '{gauge.name}': corners that bend little in the profile ({corners}; corner detection merges "
            f"faces bending by less than min_corner_angle, {needed:.1f} deg): expect profiles refused with "
            f"'corner detection: found {gauge.n_ridges - 1} corners' where they do. A gauge's corners should bend by "
            f"10 deg or more (profile_pose gauge check)")


def _at_most(rule: str, value: float, limit: float, unit: str, slack: float = 0.0) -> RuleCheck:
    return RuleCheck(rule, float(value), float(limit), bool(value <= limit + slack), unit)


def _at_least(rule: str, value: float, limit: float, unit: str, slack: float = 0.0) -> RuleCheck:
    return RuleCheck(rule, float(value), float(limit), bool(value >= limit - slack), unit)


def check_rules(gauge: Gauge, rules: RandomGaugeRules = RandomGaugeRules(),
                profiler: ProfilerModel = DEFAULT_PROFILER, min_corner_angle_deg: float = 10.0) -> list[RuleCheck]:
    """Every fabrication and visibility rule with its value, its limit and whether it holds (lengths in mm)."""
    seen = corners_visible(gauge, *nominal_pose(gauge, profiler), profiler)
    return [
        _at_most("steepest face from horizontal", np.max(gauge.face_slope_deg()), rules.max_face_angle_deg, "deg",
                 1e-9),
        _at_least("narrowest face (either end)", np.min(face_widths(gauge)) * 1e3, rules.min_face_width * 1e3, "mm",
                  1e-9),
        _at_least("smallest bend between adjacent faces", np.min(adjacent_face_angles_deg(gauge)),
                  min_corner_angle_deg, "deg"),
        _at_least("smallest bend in the profile (poses drawn from the pose range)",
                  np.min(weakest_profile_bends_deg(gauge)), min_corner_angle_deg, "deg"),
        _at_least(f"ridge directions >= {rules.min_ridge_separation_deg:g} deg apart",
                  distinct_directions(np.arctan(gauge.u), rules.min_ridge_separation_deg), 4, "ridges"),
        _at_most("relief (highest - lowest top point)", np.ptp(gauge.corner_heights()) * 1e3, rules.max_relief * 1e3,
                 "mm", 1e-9),
        RuleCheck("width against the profiler's near field of view", gauge.width * 1e3, profiler.width_near * 1e3,
                  bool(gauge.width < profiler.width_near), "mm"),
        RuleCheck("all corners seen at the nominal pose", float(seen), 1.0, bool(seen), ""),
    ]


def nominal_pose(gauge: Gauge, profiler: ProfilerModel = DEFAULT_PROFILER) -> tuple[np.ndarray, np.ndarray]:
    """Straight down over the gauge centre, its mid-height in the middle of the depth range."""
    standoff = 0.5 * (profiler.z_near + profiler.z_far)
    return LOOKING_DOWN.copy(), np.array([0.0, 0.0, mid_height(gauge) + standoff])


def _reach(visible, step: float, limit: float) -> float:
    """How far (>= 0) a one-parameter move can go from 0 with visible(s) true: coarse steps, then bisection."""
    if not visible(0.0):
        return 0.0
    good = 0.0
    while good + step <= limit and visible(good + step):
        good += step
    bad = min(good + step, limit)
    if bad == good:
        return good
    for _ in range(12):
        middle = 0.5 * (good + bad)
        good, bad = (middle, bad) if visible(middle) else (good, middle)
    return good


@dataclass(frozen=True)
class MotionRange:
    """Permissible moves from the nominal pose: [negative side, positive side] each (m or rad)."""

    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]
    alpha: tuple[float, float]  # tilt in the laser plane (incidence angle from the vertical)

    def span(self, axis: str) -> float:
        return float(sum(getattr(self, axis)))


def range_of_motion(gauge: Gauge, profiler: ProfilerModel = DEFAULT_PROFILER) -> MotionRange:
    rotation, translation = nominal_pose(gauge, profiler)

    def shifted(axis: np.ndarray, sign: float):
        return lambda s: corners_visible(gauge, rotation, translation + sign * s * axis, profiler)

    aim = translation + (0.5 * (profiler.z_near + profiler.z_far)) * rotation[:, 2]

    def tilted(sign: float):
        """Tilt in the laser plane about the point the profiler aims at, so only the incidence changes."""
        def visible(a: float) -> bool:
            turned = rotation @ so3_exp(np.array([0.0, sign * a, 0.0]))
            return corners_visible(gauge, turned, aim - (aim - translation) @ rotation[:, 2] * turned[:, 2], profiler)
        return visible

    def both(make, step: float, limit: float) -> tuple[float, float]:
        return _reach(make(-1.0), step, limit), _reach(make(1.0), step, limit)

    return MotionRange(
        x=both(lambda s: shifted(rotation[:, 0], s), 2e-3, 0.3),
        y=both(lambda s: shifted(np.array([0.0, 1.0, 0.0]), s), 2e-3, 0.3),
        z=both(lambda s: shifted(rotation[:, 2], s), 5e-3, 0.4),
        alpha=both(tilted, np.radians(1.0), np.radians(80.0)),
    )


def occlusion_beta_deg(gauge: Gauge) -> float:
    """beta: smallest angle between a top face and the vertical; alpha beyond it self-occludes (Fig. 4b)."""
    return float(90.0 - np.max(gauge.face_slope_deg()))


@dataclass(frozen=True)
class RequiredMotion:
    """A range of motion the cell needs, about the nominal pose (design and precision checks)."""

    x: float = 0.010  # m, +- along the profiler's x
    y: float = 0.010  # m, +- along the gauge's y
    standoff: tuple[float, float] = (0.35, 0.55)  # m, profiler to the gauge's mid-height
    tilt: float = np.radians(10.0)  # rad, of the profiler's z from straight down
    yaw: float = np.radians(10.0)  # rad, of the laser line about the vertical


def motion_poses(gauge: Gauge, motion: RequiredMotion = RequiredMotion(), thorough: bool = False) -> list[tuple]:
    """Poses at the extremes of the motion: (label, R, t). thorough=True: every combination (80 poses),
    else 16 that still visit every extreme of every axis (for the design search's inner loop)."""
    middle = mid_height(gauge)
    tilts = [None, 0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi]
    poses = []
    index = 0
    for standoff in motion.standoff:
        for tilt_azimuth in tilts:
            for yaw_sign in (-1.0, 1.0):
                for sx, sy in ((-1, -1), (1, 1), (-1, 1), (1, -1)):
                    index += 1
                    if not thorough and (index % 5) not in (0, 3):
                        continue
                    tilt = np.zeros(3) if tilt_azimuth is None else motion.tilt * np.array(
                        [np.cos(tilt_azimuth), np.sin(tilt_azimuth), 0.0])
                    rotation = so3_exp(tilt) @ so3_exp(np.array([0.0, 0.0, yaw_sign * motion.yaw])) @ LOOKING_DOWN
                    aim = np.array([sx * motion.x, sy * motion.y, middle])
                    label = (f"standoff {standoff * 1e3:.0f} mm, tilt "
                             f"{'0' if tilt_azimuth is None else f'{np.degrees(motion.tilt):.0f} deg @ {np.degrees(tilt_azimuth):.0f}'}"
                             f", yaw {yaw_sign * np.degrees(motion.yaw):+.0f} deg, x {sx * motion.x * 1e3:+.0f} y "
                             f"{sy * motion.y * 1e3:+.0f} mm")
                    poses.append((label, rotation, aim - standoff * rotation[:, 2]))
    return poses


@dataclass(frozen=True)
class PoseBound:
    label: str
    visible: bool
    corner_position: float = float("nan")  # m, rms of the corner-model CRLB
    corner_rotation: float = float("nan")  # rad
    dense_position: float = float("nan")
    dense_rotation: float = float("nan")


def precision_over(gauge: Gauge, poses: list[tuple], noise_std: float, dense: bool = True,
                   profiler: ProfilerModel = DEFAULT_PROFILER) -> list[PoseBound]:
    """The Cramér-Rao bounds at each pose (a pose whose corners are not all seen is marked, not bounded)."""
    bounds = []
    for label, rotation, translation in poses:
        if not corners_visible(gauge, rotation, translation, profiler):
            bounds.append(PoseBound(label, False))
            continue
        try:
            corner = position_rotation_rms(corner_crlb(gauge, rotation, translation, noise_std, profiler))
        except (ValueError, np.linalg.LinAlgError):
            bounds.append(PoseBound(label, False))
            continue
        dense_bound = (position_rotation_rms(dense_crlb(gauge, rotation, translation, noise_std, profiler))
                       if dense else (float("nan"), float("nan")))
        bounds.append(PoseBound(label, True, *corner, *dense_bound))
    return bounds


def worst_bound(bounds: list[PoseBound]) -> tuple[float, float]:
    """(worst corner-model position, rotation) over the poses; inf if any pose loses a corner."""
    if not bounds or not all(b.visible for b in bounds):
        return float("inf"), float("inf")
    return max(b.corner_position for b in bounds), max(b.corner_rotation for b in bounds)
