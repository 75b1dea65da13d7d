"""profile_pose gauge: each design rule fails on a hand-made gauge that breaks it; check, design and export
work end to end; the STL is a closed solid by trimesh's own tests."""
import json
import re

import numpy as np
import pytest
import trimesh
import yaml

from conftest import PAPER_GAUGE
from profile_pose_ros.core import EstimatorOptions, Gauge, estimate_pose, render_profile, sample_pose
from profile_pose_ros.core.design.gauge_check import (RequiredMotion, check_rules, motion_poses, narrow_face_warning,
                                                      narrowest_profile_faces, profile_pitch, range_of_motion,
                                                      weak_corner_warning, weakest_profile_bends_deg)
from profile_pose_ros.core.design.gauge_design import RandomGaugeRules, heightfield_gauge
from profile_pose_ros.core.model.gauge_mesh import gauge_mesh
from profile_pose_ros.core.design.gauge_search import INVALID, DesignSpace
from profile_pose_ros.tools import gauge_cli

RULES = RandomGaugeRules(min_face_width=0.0035)


def made(width=0.120, length=0.100, ridge_x=(-0.038, -0.019, 0.0, 0.019, 0.038), angles_deg=(-20, -10, 0, 10, 20),
         slopes=(0.6, -0.57, 0.63, -0.6, 0.63, -0.57), min_height=0.015) -> Gauge:
    return heightfield_gauge("hand_made", width, length, np.array(ridge_x), np.radians(angles_deg), np.array(slopes),
                             min_height=min_height)


def failing(gauge: Gauge) -> set[str]:
    return {c.rule for c in check_rules(gauge, RULES) if not c.ok}


def test_hand_made_paper_like_gauge_keeps_every_rule():
    assert failing(made()) == set()


@pytest.mark.parametrize("gauge, rule", [
    (made(slopes=(0.6, -0.57, 1.2, -0.6, 0.63, -0.57)), "steepest face from horizontal"),
    (made(ridge_x=(-0.038, -0.019, 0.0, 0.003, 0.038), angles_deg=(-20, -10, 0, 1, 20)), "narrowest face (either end)"),
    (made(slopes=(0.6, -0.57, 0.63, 0.55, 0.63, -0.57)), "smallest bend between adjacent faces"),
    (made(slopes=(0.6, -0.57, 0.63, 0.60, -0.6, 0.6)), "smallest bend in the profile (poses drawn from the pose range)"),
    (made(angles_deg=(-4, -2, 0, 2, 4)), "ridge directions >= 3 deg apart"),
    (made(slopes=(0.8, -0.3, 0.8, -0.3, 0.8, -0.3)), "relief (highest - lowest top point)"),
    (made(width=0.170, ridge_x=(-0.05, -0.025, 0.0, 0.025, 0.05)), "width against the profiler's near field of view"),
])
def test_each_rule_fails_on_a_gauge_that_breaks_it(gauge, rule):
    assert rule in failing(gauge)


def test_a_corner_the_profile_hardly_shows_is_named_and_its_profiles_are_refused():
    """Faces 2 and 3 bend by about 1 deg in every profile: corner detection merges them (min_corner_angle 5 deg)
    and refuses the profile, never a pose; the check names that corner and no other, and the node's start-up
    warning says what to expect."""
    weak = made(slopes=(0.6, -0.57, 0.63, 0.60, -0.6, 0.6))
    bends = weakest_profile_bends_deg(weak)
    assert np.flatnonzero(bends < 10.0).tolist() == [2] and bends[2] < 2.0
    rng = np.random.default_rng(1)
    for _ in range(5):
        estimate = estimate_pose(render_profile(weak, *sample_pose(weak, rng), noise_std=5e-6, rng=rng), weak)
        assert not estimate.ok and estimate.reason.startswith("corner detection: found 4 corners"), estimate.reason
    warning = weak_corner_warning(weak, EstimatorOptions().corners.min_corner_angle)
    assert "faces 2/3 as little as" in warning and "faces 1/2" not in warning
    assert weak_corner_warning(made(), EstimatorOptions().corners.min_corner_angle) is None


def test_a_face_too_narrow_for_a_thinned_profile_is_named_and_the_suggested_setting_keeps_it():
    """Face 3 spans 4.3-6 mm of the profile: 57 points or more at the profiler's full 0.075 mm pitch, 14 at a
    quarter of its points (binning or thinning, 0.3 mm), under min_segment_points (20), and detection then refuses
    the profile as corners short; the check says so only at the coarse pitch, and its suggestion keeps the face."""
    narrow = made(ridge_x=(-0.038, -0.019, 0.0, 0.005, 0.038), angles_deg=(-20, -10, 0, 3, 20))
    widths = narrowest_profile_faces(narrow)
    assert np.argmin(widths) == 2 and 4e-3 < widths[2] < 4.5e-3 and np.delete(widths, 2).min() > 15e-3
    rng = np.random.default_rng(1)
    profiles = [render_profile(narrow, *sample_pose(narrow, rng), noise_std=5e-6, rng=rng) for _ in range(8)]
    fine, coarse = profile_pitch(profiles[0]), profile_pitch(profiles[0][::4])
    assert np.isclose(fine, 75e-6) and np.isclose(coarse, 300e-6) and profile_pitch(profiles[0][::-1]) == fine
    assert narrow_face_warning(narrow, 20, fine, widths) is None and narrow_face_warning(narrow, 20, np.nan) is None
    warning = narrow_face_warning(narrow, 20, coarse, widths)
    assert "face 3 as little as 4.3 mm, 14 points" in warning and "face 2" not in warning, warning
    suggested = int(re.search(r"min_segment_points near (\d+)", warning).group(1))
    for profile in profiles:
        assert estimate_pose(profile, narrow).ok
        refused = estimate_pose(profile[::4], narrow)
        assert not refused.ok and refused.reason.startswith("corner detection: found"), refused.reason
        assert estimate_pose(profile[::4], narrow, min_segment_points=suggested).ok


def test_corners_unseen_at_the_nominal_pose_is_a_failure():
    sawtooth = made(ridge_x=(-0.04, -0.02, 0.0, 0.02, 0.04), angles_deg=(-10, -5, 0, 5, 10),
                    slopes=(6.0, -6.0, 6.0, -6.0, 6.0, -6.0))  # 80 deg faces: the fan cannot see into the valleys
    assert "all corners seen at the nominal pose" in failing(sawtooth)


def test_range_of_motion_shrinks_with_a_wider_gauge():
    narrow = range_of_motion(made(width=0.100, ridge_x=(-0.03, -0.015, 0.0, 0.015, 0.03)))
    wide = range_of_motion(made(width=0.140, ridge_x=(-0.045, -0.022, 0.0, 0.022, 0.045)))
    assert narrow.span("x") > wide.span("x") + 0.03  # Fig. 4a: margins shrink linearly with size
    assert narrow.span("y") == pytest.approx(0.1, abs=1e-3)  # along y: the gauge's length


def test_stl_of_both_gauges_is_watertight(tmp_path):
    for gauge in (Gauge.from_yaml(PAPER_GAUGE), made(angles_deg=(-15, -12, 0, 15, 17), slopes=(0.3, -0.7, 0.5, -0.3, 0.7, -0.4))):
        mesh = gauge_mesh(gauge)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
        xs, ys = np.meshgrid(np.linspace(-gauge.width / 2, gauge.width / 2, 400),
                             np.linspace(-gauge.length / 2, gauge.length / 2, 400))
        integral = np.mean(gauge.surface_z(xs, ys) - gauge.base_z) * gauge.width * gauge.length
        assert mesh.volume == pytest.approx(integral, rel=2e-3)
    out = tmp_path / "paper.stl"
    assert gauge_cli.main(["export", str(PAPER_GAUGE), "--out", str(out)]) == 0
    loaded = trimesh.load(out)
    assert loaded.is_watertight
    assert loaded.bounds[1][0] == pytest.approx(60.0, abs=1e-3)  # millimetres


def test_check_command_on_the_shipped_gauge(tmp_path, capsys):
    assert gauge_cli.main(["check", str(PAPER_GAUGE), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "VALID" in printed and "Range of motion" in printed
    report = json.loads(next(tmp_path.glob("*/check.json")).read_text())
    assert report["failed"] == []
    assert 1e-4 < report["worst_position_m"] < 5e-4
    assert len(report["monte_carlo"]) == 2 and all(mc["rejected"] == 0 for mc in report["monte_carlo"].values())
    worst = max(report["bounds"], key=lambda b: b["corner_position"])  # the estimator reaches the bound there
    assert 0.8 < report["monte_carlo"][worst["label"]]["position_rms"] / worst["corner_position"] < 1.25


def test_check_command_says_which_rule_fails(tmp_path, capsys):
    path = tmp_path / "steep.yaml"
    path.write_text(yaml.safe_dump(made(slopes=(0.6, -0.57, 1.2, -0.6, 0.63, -0.57)).to_dict()))
    assert gauge_cli.main(["check", str(path), "--out", str(tmp_path)]) == 1
    assert "NOT VALID: steepest face from horizontal" in capsys.readouterr().out


def test_design_scores_invalid_designs_worse_than_any_valid_one():
    space = DesignSpace(5, (0.10, 0.14), RULES, RequiredMotion(), 5e-6, (1.9e-4, 3.6e-4))
    spread = [0.1, 0.3, 0.5, 0.7, 0.9]
    x = np.array([0.12, 0.1, *spread, 0.0, 0.05, 0.5, 0.95, 1.0, *[0.6] * 6, 0.0, 1.0])  # width, length, ridge ends, slopes, ...
    assert len(x) == len(space.bounds())
    valid = space.score(x)
    assert 0 < valid < 10
    steep = x.copy()
    steep[2 + 10:2 + 16] = 2.0  # 63 deg faces
    assert space.score(steep) >= INVALID / 2


def test_design_command_end_to_end(tmp_path, capsys):
    out = tmp_path / "designed.yaml"
    assert gauge_cli.main(["design", "--out", str(out), "--ridges", "4", "--generations", "2", "--population", "3",
                           "--workers", "1", "--tilt", "5", "--yaw", "5"]) == 0
    designed = Gauge.from_yaml(out)
    assert designed.n_ridges == 4
    assert "worst CRLB pos" in capsys.readouterr().out
    assert all(c.ok for c in check_rules(designed, RULES))
    assert motion_poses(designed, RequiredMotion(), thorough=True)
