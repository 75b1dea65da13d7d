"""The benchmark cannot rot: its quick mode runs end to end (speed itself is not asserted: CI is noisy),
and its plain reference solves the same problem as the runtime path."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from profile_pose_ros.core import estimate_pose, render_profile, sample_pose
from profile_pose_ros.tools.numpy_baseline import estimate_baseline


def run_quick(tool: str, report_name: str, out: Path, *extra: str) -> tuple[str, dict]:
    """Run `profile_pose <tool>` in its --quick mode; its stdout and the JSON report it wrote."""
    exe = Path(sys.executable).parent / "profile_pose"
    result = subprocess.run([str(exe), tool, "--quick", "--out", str(out), *extra], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    (report,) = out.glob(f"*/{report_name}")
    return result.stdout, json.loads(report.read_text())


def test_quick_benchmark_runs_and_reports_every_row(tmp_path):
    stdout, data = run_quick("benchmark", "benchmark.json", tmp_path)
    for row in ("Proposed, this package: CD", "Proposed, this package: total (one call)", "Numpy baseline: total",
                "Camera-based (OpenCV): CD", "Camera-based (OpenCV): PC"):
        assert data["stages_ms"][row]["n"] > 0, row
        assert data["stages_ms"][row]["median"] > 0
    assert set(data["ratios"]) == {"baseline / ours (median total)", "camera / ours (median CD + PC)"}
    assert data["data_bytes"]["profile (3200 x float32)"] == 12800
    assert "time per measurement (ms)" in stdout


def test_numpy_baseline_solves_the_same_problem(gauge, rng):
    for _ in range(20):
        points = render_profile(gauge, *sample_pose(gauge, rng), noise_std=5e-6, rng=rng)
        ours = estimate_pose(points, gauge)
        rotation, translation, _ = estimate_baseline(points, gauge)
        assert np.max(np.abs(translation - ours.t)) < 1e-7  # scipy's LM stops on its own tolerances
        assert np.max(np.abs(rotation - ours.R)) < 1e-7


@pytest.mark.alone  # loads the machine at 1 kHz
def test_quick_node_benchmark_runs_both_rates(tmp_path):
    stdout, data = run_quick("node-benchmark", "node_benchmark.json", tmp_path)
    runs = data["runs"]
    assert "pose_estimator under load" in stdout
    assert [(r["rate_hz"], r["node"]) for r in runs] == [(83.3, "null"), (83.3, "pose_estimator"),
                                                          (1000.0, "null"), (1000.0, "pose_estimator")]
    assert "the estimator adds" in stdout
    for r in runs:
        own = r["node_window_p99_ms"]  # the estimator's diagnostics; the null node has none
        assert (own == []) if r["node"] == "null" else all(p99 > 0 for p99 in own)
        assert r["sent"] > 0 and 0 < r["received"] <= r["sent"]
        assert r["latency_ms"]["median"] > 0 and r["peak_rss_mib"] > 0 and r["cpu_share"] > 0


def test_the_null_node_queues_as_many_profiles_as_the_estimator():
    """The floor is only a floor if the null node takes profiles as the estimator does."""
    from profile_pose_ros.nodes.pose_estimator import PARAMETERS
    from profile_pose_ros.tools.null_node import QUEUE_DEPTH

    (queue_depth,) = [p.default for p in PARAMETERS if p.name == "queue_depth"]
    assert QUEUE_DEPTH == queue_depth


def test_quick_study_runs_end_to_end(tmp_path):
    stdout, data = run_quick("study", "study.json", tmp_path)
    assert "TABLE I" in stdout and "Fig. 3" in stdout
    assert set(data["figure_three"]) == {"0 um", "5 um", "25 um", "45 um"}
    assert data["figure_three"]["0 um"]["ref_reproj"]["mean"] < 1e-3  # noise-free: exact
    for n in (4, 5):
        row = data["table_one"][f"n={n}"]
        # the corner model refuses a random gauge's views determined worse than max_position_sigma (0.35 mm):
        # 20-35 % of n = 4 views (profile_pose robustness), so 20 quick poses stay well under 3/4 refused
        assert row["failure_rate"] < 0.75 and row["corner_crlb_pos_rms_um"] > 0 and row["dense_crlb_pos_rms_um"] > 0
        assert row["wrong_minima"] == 0 and 0 <= row["searched_share"] <= 1
    assert "Outliers" in stdout and "Dense refinement" in stdout
    assert data["outliers"]["1 % spikes, this package (robust fits)"]["poses"] == 4 * 5
    assert data["dense"]["poses"] == 20 and data["dense"]["failed"] == 0
    assert list(tmp_path.glob("*/fig3_noise.png"))


def test_quick_robustness_runs_every_condition_and_the_shipped_gauges_publish_no_wrong_pose(tmp_path):
    stdout, data = run_quick("robustness", "robustness.json", tmp_path, "--bound", "--repeats", "2")
    cells = data["cells"]
    conditions = {name.split(" | ")[1] for name in cells}
    assert {"clean", "spikes 5 %", "gap over a corner", "gap between corners", "noise 45 um",
            "glints 2 % (runs of 3-8)", "glints 5 % (runs of 3-8)"} <= conditions
    shipped = {k: c for k, c in cells.items() if k.startswith("gauge_")}
    assert shipped and all(c["wrong_pct"] == 0 for c in shipped.values())
    assert all(shipped[f"{gauge} | {condition}"]["refused_pct"] == 0
               for gauge in ("gauge_paper_n5.yaml", "gauge_designed_n6.yaml")
               for condition in ("spikes 0.5 %", "spikes 1 %", "spikes 2 %", "spikes 5 %", "glints 2 % (runs of 3-8)",
                                 "glints 5 % (runs of 3-8)"))
    assert "profiles," in stdout and "accepted" in stdout
    # --bound: every cell that refused something holds its refusals against the Cramer-Rao bound
    refusing = [c for c in cells.values() if c["refused_pct"] > 0]
    assert refusing and all(0 <= c["refused_beyond_bound_pct"] <= c["refused_pct"] + 1e-9 for c in refusing)
    assert all(c["wrong_if_refused_published"] >= 0 for c in refusing) and "refused beyond bound %" in stdout
    # and every cell the wrong poses its accepted poses' covariances predict: none of the shipped gauges' clean ones
    assert all(c["wrong_expected"] >= 0 for c in cells.values()) and "expected from the accepted poses" in stdout
    assert shipped["gauge_paper_n5.yaml | clean"]["wrong_expected"] < 1e-3
    # --repeats: each profile's fastest call beside its first, never slower at any percentile
    assert all(c["fastest_ms"][k] <= c["time_ms"][k] for c in cells.values() for k in ("median", "p99"))
    assert "fastest of 2" in stdout


def test_gates_judge_an_opened_estimator_as_the_gated_one_would_have_and_give_the_trade(tmp_path):
    """--gates opens the estimator's gate and judges each pose by the configured one afterwards: its main table
    must be the plain run's, cell by cell, or the trade it prints is of another estimator."""
    families = ("--families", "gauge_paper_n5.yaml", "random n=5")
    _, plain = run_quick("robustness", "robustness.json", tmp_path / "plain", *families)
    stdout, gated = run_quick("robustness", "robustness.json", tmp_path / "gated", *families,
                              "--gates", "0.2", "0.35", "2")
    assert gated["cells"].keys() == plain["cells"].keys()
    for name, cell in plain["cells"].items():
        for figure in ("refused_pct", "wrong", "nees_mean", "top_refusal"):
            assert gated["cells"][name][figure] == pytest.approx(cell[figure], nan_ok=True), (name, figure)
    frontier = gated["gates"]
    assert [row["gate_mm"] for row in frontier] == [0.2, 0.35, 2.0] and "What the precision gate trades" in stdout
    configured = frontier[1]
    accepted = sum(c["profiles"] * (1 - c["refused_pct"] / 100) for c in plain["cells"].values())
    assert configured["accepted"] == round(accepted)
    assert configured["profiles"] == sum(c["profiles"] for c in plain["cells"].values())
    # a looser gate refuses no more and publishes no fewer poses, nor predicts fewer wrong ones
    for tighter, looser in zip(frontier, frontier[1:]):
        assert looser["accepted"] >= tighter["accepted"] and looser["wrong_expected"] >= tighter["wrong_expected"]
        assert looser["worst_refused_pct"] <= tighter["worst_refused_pct"]
    assert frontier[2]["accepted"] > frontier[0]["accepted"]  # random views at 25-45 um sit between 0.2 and 2 mm
    bands = gated["nees_by_sigma"]
    assert [band["sigma_mm"][0] for band in bands] == [0.0, 0.2, 0.35, 2.0]
    assert sum(band["poses"] for band in bands) >= frontier[2]["accepted"]


def test_a_run_of_a_few_families_sees_the_profiles_the_full_run_does():
    """A family's gauges and poses follow from the seed and the family, not from its place in --families: a
    closer look at one cell of a full run reproduces that cell."""
    from profile_pose_ros.tools.robustness import FAMILIES, _family_index

    for family in FAMILIES:
        assert _family_index(family, [family]) == _family_index(family, list(FAMILIES)) == FAMILIES.index(family)
    assert _family_index("random n=6", ["random n=5", "random n=6"]) == len(FAMILIES)
    assert _family_index("my_gauge.yaml", ["random n=6", "my_gauge.yaml"]) == len(FAMILIES) + 1


def test_the_chance_of_a_wrong_pose_is_the_gaussian_tail_of_its_covariance():
    from scipy.stats import chi2, norm

    from profile_pose_ros.tools.robustness import WRONG_POSITION, may_be_wrong, wrong_if_published

    rng = np.random.default_rng(1)
    one_axis = np.diag([WRONG_POSITION ** 2, 1e-12, 1e-12, 1e-12, 1e-12, 1e-12])  # std 1 mm along x only
    assert wrong_if_published(one_axis, rng=rng) == pytest.approx(2 * norm.sf(1.0), abs=0.01)
    round_ball = np.diag([(WRONG_POSITION / 2) ** 2] * 3 + [1e-12] * 3)  # 0.5 mm on each axis
    assert wrong_if_published(round_ball, rng=rng) == pytest.approx(chi2.sf(4.0, 3), abs=0.01)
    assert may_be_wrong(one_axis) and not may_be_wrong(np.diag([(WRONG_POSITION / 7) ** 2] * 3 + [1e-12] * 3))
