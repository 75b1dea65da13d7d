"""profile_pose study: the paper's simulation study (III-B, III-C) with true errors and Cramér-Rao bounds.

Table I: n in {4, 5, 7, 10} ridges x m in {10, 50, 100, 150} random gauges (nested subsets of the same
150) x 100 random poses at 5 um depth noise: mean/std of the reprojection error (eq. 17 as a length) for
the paper's closed form (CF; for n = 4 its minimum-norm solution, as the paper's) and the refined solution
(CF-Opt, for n = 4 started from our null-space candidates), with the paper's notation ('-' when the mean
exceeds 1000 um, '*' below 1 um). Beyond the paper, per n: the true position and rotation errors, the
failure rate, the corner-model and dense-model Cramér-Rao bounds, the estimator's efficiency (rms error /
rms bound), the NEES of the refined pose against its covariance and the wrong minima with and without the
basin search; outliers (n = 5, 1 % spikes: robust pipeline vs the paper's plain one); dense refinement vs
corner-based on the shipped gauge.
Fig. 3: n = 5, the same 150 gauges x 100 poses at 0, 5, ..., 45 um, the paper's CF and CF-Opt (refined
from the CF, no basin search); printed and plotted against noise.
Both cores are used; --quick gives a reduced run for tests.
"""
from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from ..core import estimate_pose, pose_error, render_profile, sample_pose
from ..core.design.crlb import corner_crlb, dense_crlb, position_rotation_rms
from ..core.estimation.estimator import is_wrong_minimum, pose_nees
from ..core.estimation.stages import detect_corners
from ..core.design.gauge_design import random_gauge
from ..core.compiled.render_kernel import trace_depth_fast
from .numpy_baseline import paper_closed_form
from .report import run_dir, summary, table, write_json

TABLE_NOISE = 5e-6
FAIL_UM = 1000.0  # the paper's '-' rule


SPIKES = 0.01  # share of profile points replaced by spikes in the outlier study
SPIKE_RANGE = (2e-4, 2e-3)  # m, spike magnitude (either sign)
# plain fits, eq. 15, one start, every refined pose kept
PAPER_PIPELINE = {"robust_line_fit": False, "spike_threshold": 0.0, "refine_weighting": "uniform",
                  "refine_model": "corners", "basin_search": False, "max_position_sigma": np.inf,
                  "max_residual_ratio": np.inf, "hidden_faces": False}


def error_row(gauge, estimate, rotation, t, n: int) -> list[float]:
    """[cf_reproj, cf_pos, cf_rot, ref_reproj, ref_pos, ref_rot, nees] of one estimate (NaN if rejected)."""
    if not estimate.ok or estimate.closed_form is None:
        return [np.nan] * 7
    cf = estimate.closed_form if n > 4 else paper_closed_form(gauge, estimate.corners)
    return [cf.reprojection_error, *pose_error(cf.rotation, cf.translation, rotation, t), estimate.reprojection_error,
            *pose_error(estimate.R, estimate.t, rotation, t), pose_nees(estimate, rotation, t)]


def wrong_minimum(points, gauge, estimate, rotation, t, corner_cov) -> float:
    """1.0 / 0.0 for an accepted estimate (estimator.is_wrong_minimum), NaN for a rejected one."""
    if not estimate.ok:
        return np.nan
    return float(is_wrong_minimum(points, gauge, estimate, rotation, t, corner_cov))


def bound_rms(gauge, rotation, t, with_dense: bool) -> list[float]:
    """[corner CRLB pos, rot, dense CRLB pos, rot] (rms, m and rad) at TABLE_NOISE; dense NaN unless asked."""
    corner = position_rotation_rms(corner_crlb(gauge, rotation, t, TABLE_NOISE, trace=trace_depth_fast,
                                               detect=detect_corners))
    if not with_dense:
        return [*corner, np.nan, np.nan]
    return [*corner, *position_rotation_rms(dense_crlb(gauge, rotation, t, TABLE_NOISE, trace=trace_depth_fast))]


def gauge_trial(task: tuple) -> dict:
    """One random gauge: every pose at every noise level, and at TABLE_NOISE the bounds and comparisons.

    Fig. 3 rows use the paper's CF-Opt (refined from the closed form, no basin search); Table I rows use
    the package's estimator (basin search on) and also count wrong minima with and without the search.
    n = 5 poses are also estimated from a copy of the profile with 1 % spikes, by the package's robust
    pipeline and by the paper's plain one.
    """
    n, seed, poses, noises, with_dense = task
    rng = np.random.default_rng(seed)
    gauge = random_gauge(n, rng)
    rows = {noise: [] for noise in noises}
    table, bounds, extra = [], [], []
    for _ in range(poses):
        rotation, t = sample_pose(gauge, rng, trace=trace_depth_fast)
        for noise in noises:
            points = render_profile(gauge, rotation, t, noise_std=noise, rng=rng, trace=trace_depth_fast)
            paper = estimate_pose(points, gauge, max_reprojection_error=1.0, refine_model="corners",
                                  basin_search=False, max_position_sigma=np.inf, max_residual_ratio=np.inf)
            row = error_row(gauge, paper, rotation, t, n)
            rows[noise].append(row if noise > 0 else row[:6] + [np.nan])
            if noise != TABLE_NOISE:
                continue
            # the package's corner model beside the paper's (the dense model has its own columns, below)
            ours = estimate_pose(points, gauge, max_reprojection_error=1.0, refine_model="corners")
            table.append(error_row(gauge, ours, rotation, t, n))
            spiky_ours = spiky_paper = np.nan
            if n == 5:
                spiky = render_profile(gauge, rotation, t, noise_std=noise, rng=rng, spike_fraction=SPIKES,
                                       spike_range=SPIKE_RANGE, trace=trace_depth_fast)
                spiky_ours = error_row(gauge, estimate_pose(spiky, gauge, max_reprojection_error=1.0,
                                                            refine_model="corners"), rotation, t,
                                       n)[4]
                spiky_paper = error_row(gauge, estimate_pose(spiky, gauge, max_reprojection_error=1.0,
                                                             **PAPER_PIPELINE), rotation, t, n)[4]
            found = detect_corners(points, n) if ours.ok or paper.ok else None  # once for both checks
            corner_cov = found.covariance(None) if found is not None and found.ok else None
            extra.append([wrong_minimum(points, gauge, ours, rotation, t, corner_cov),
                          wrong_minimum(points, gauge, paper, rotation, t, corner_cov),
                          float(ours.search_starts > 0),
                          spiky_ours, spiky_paper])
            bounds.append(bound_rms(gauge, rotation, t, with_dense))
    return {"n": n, "seed": seed, "rows": {noise: np.array(r) for noise, r in rows.items()},
            "table": np.array(table), "extra": np.array(extra), "bounds": np.array(bounds)}


EXTRA = ["wrong_min", "wrong_min_no_search", "searched", "spiky_pos", "spiky_pos_paper"]


def dense_trial(task: tuple) -> np.ndarray:
    """The shipped gauge at TABLE_NOISE: [corner pos, corner rot, dense pos, dense rot, both bounds] per pose."""
    seed, poses = task
    from ..core.model.gauge import Gauge
    from ..resources import DEFAULT_GAUGE, config_path

    gauge = Gauge.from_yaml(config_path(DEFAULT_GAUGE))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(poses):
        rotation, t = sample_pose(gauge, rng, trace=trace_depth_fast)
        points = render_profile(gauge, rotation, t, noise_std=TABLE_NOISE, rng=rng, trace=trace_depth_fast)
        row = []
        for model in ("corners", "dense"):
            estimate = estimate_pose(points, gauge, refine_model=model)
            row += list(pose_error(estimate.R, estimate.t, rotation, t)) if estimate.ok else [np.nan, np.nan]
        row += bound_rms(gauge, rotation, t, with_dense=True)
        out.append(row)
    return np.array(out)


COLUMNS = ["cf_reproj", "cf_pos", "cf_rot", "ref_reproj", "ref_pos", "ref_rot", "nees"]


def paper_cell(values_um: np.ndarray) -> str:
    """The paper's mean/std cell: '-' above 1000 um, '*' below 1 um."""
    def one(v: float) -> str:
        return "-" if not np.isfinite(v) or v > FAIL_UM else ("*" if v < 1.0 else f"{v:.0f}")
    return f"{one(np.nanmean(values_um))}/{one(np.nanstd(values_um))}"


def table_one(results: list[dict], ns, ms) -> tuple[str, str, dict]:
    paper_rows, extra_rows, data = [], [], {}
    for method, key in (("CF", "cf_reproj"), ("CF-Opt", "ref_reproj")):
        for n in ns:
            cells = []
            for m in ms:
                stack = np.concatenate([r["table"] for r in results if r["n"] == n][:m])
                values = stack[:, COLUMNS.index(key)] * 1e6
                cells.append(paper_cell(values))
                data[f"{method} n={n} m={m}"] = summary(values[np.isfinite(values)])
            paper_rows.append([method if n == ns[0] else "", str(n), *cells])
    for n in ns:
        mine = [r for r in results if r["n"] == n][:max(ms)]
        stack = np.concatenate([r["table"] for r in mine])
        extra = np.concatenate([r["extra"] for r in mine])
        bounds = np.concatenate([r["bounds"] for r in mine])
        failed = ~np.isfinite(stack[:, 3]) | (stack[:, 3] * 1e6 > FAIL_UM)
        good = stack[~failed]
        rms = lambda col: float(np.sqrt(np.mean(good[:, COLUMNS.index(col)] ** 2)))  # noqa: E731
        corner_pos = float(np.sqrt(np.mean(bounds[~failed, 0] ** 2)))
        dense_pos = float(np.sqrt(np.nanmean(bounds[~failed, 2] ** 2)))
        count = lambda col: int(np.nansum(extra[:, EXTRA.index(col)]))  # noqa: E731
        row = {"poses": int(len(stack)), "failure_rate": float(failed.mean()),
               "ref_pos_rms_um": rms("ref_pos") * 1e6, "ref_pos_median_um": float(np.median(good[:, 4])) * 1e6,
               "ref_rot_rms_urad": rms("ref_rot") * 1e6, "cf_pos_median_um": float(np.nanmedian(stack[:, 1])) * 1e6,
               "corner_crlb_pos_rms_um": corner_pos * 1e6, "dense_crlb_pos_rms_um": dense_pos * 1e6,
               "efficiency_pos": rms("ref_pos") / corner_pos, "nees_mean": float(np.nanmean(good[:, 6])),
               "nees_median": float(np.nanmedian(good[:, 6])), "wrong_minima": count("wrong_min"),
               "wrong_minima_without_search": count("wrong_min_no_search"),
               "searched_share": float(np.nanmean(extra[:, EXTRA.index("searched")]))}
        data[f"n={n}"] = row
        extra_rows.append([str(n), str(row["poses"]), f"{100 * row['failure_rate']:.1f} %", row["cf_pos_median_um"],
                           row["ref_pos_median_um"], row["ref_pos_rms_um"], row["ref_rot_rms_urad"],
                           row["corner_crlb_pos_rms_um"], row["dense_crlb_pos_rms_um"], row["efficiency_pos"],
                           row["nees_mean"], f"{row['wrong_minima']} / {row['wrong_minima_without_search']}",
                           f"{100 * row['searched_share']:.0f} %"])
    paper = table(["", "n", *[f"m = {m}" for m in ms]], paper_rows,
                  "TABLE I: reprojection error mean/std (um), 5 um noise ('-' > 1000 um, '*' < 1 um)")
    extra = table(["n", "poses", "failed", "CF pos median (um)", "CF-Opt pos median", "CF-Opt pos rms",
                   "CF-Opt rot rms (urad)", "corner CRLB pos rms", "dense CRLB pos rms", "rms / corner CRLB",
                   "NEES mean (6)", "wrong minima (search / none)", "searched"], extra_rows,
                  f"Beyond the paper, m = {max(ms)}: true errors, bounds, covariance honesty, wrong minima")
    return paper, extra, data


def outlier_table(results: list[dict]) -> tuple[str, dict]:
    """n = 5 poses with and without 1 % spikes: the package's robust pipeline and the paper's plain one."""
    mine = [r for r in results if r["n"] == 5]
    clean = np.concatenate([r["table"][:, COLUMNS.index("ref_pos")] for r in mine])
    extra = np.concatenate([r["extra"] for r in mine])
    data, rows = {}, []
    for label, values in (("no spikes, this package", clean),
                          ("1 % spikes, this package (robust fits)", extra[:, EXTRA.index("spiky_pos")]),
                          ("1 % spikes, paper's plain pipeline", extra[:, EXTRA.index("spiky_pos_paper")])):
        ok = np.isfinite(values)
        entry = {"poses": int(len(values)), "failed": float(1 - ok.mean()),
                 "median_um": float(np.median(values[ok])) * 1e6 if ok.any() else float("nan"),
                 "rms_um": float(np.sqrt(np.mean(values[ok] ** 2))) * 1e6 if ok.any() else float("nan")}
        data[label] = entry
        rows.append([label, str(entry["poses"]), f"{100 * entry['failed']:.1f} %", entry["median_um"], entry["rms_um"]])
    data["median_ratio_spiky_over_clean"] = data["1 % spikes, this package (robust fits)"]["median_um"] / \
        data["no spikes, this package"]["median_um"]
    text = table(["n = 5, 5 um noise", "poses", "failed", "position median (um)", "position rms (um)"], rows,
                 f"Outliers: {100 * SPIKES:g} % of points replaced by spikes of +-{SPIKE_RANGE[0] * 1e3:g}-"
                 f"{SPIKE_RANGE[1] * 1e3:g} mm (median ratio spiky / clean "
                 f"{data['median_ratio_spiky_over_clean']:.3f})")
    return text, data


def dense_table(chunks: list[np.ndarray]) -> tuple[str, dict]:
    stack = np.concatenate(chunks)
    rms = lambda col: float(np.sqrt(np.nanmean(stack[:, col] ** 2))) * 1e6  # noqa: E731
    data = {"poses": int(len(stack)), "corner_pos_rms_um": rms(0), "corner_rot_rms_urad": rms(1),
            "dense_pos_rms_um": rms(2), "dense_rot_rms_urad": rms(3), "corner_crlb_pos_rms_um": rms(4),
            "corner_crlb_rot_rms_urad": rms(5), "dense_crlb_pos_rms_um": rms(6), "dense_crlb_rot_rms_urad": rms(7),
            "failed": int(np.sum(~np.isfinite(stack[:, 0]) | ~np.isfinite(stack[:, 2])))}
    data["position_gain"] = data["corner_pos_rms_um"] / data["dense_pos_rms_um"]
    rows = [["corners (paper eq. 15, ML-weighted)", data["corner_pos_rms_um"], data["corner_rot_rms_urad"],
             data["corner_crlb_pos_rms_um"], data["corner_crlb_rot_rms_urad"]],
            ["dense (every point's depth)", data["dense_pos_rms_um"], data["dense_rot_rms_urad"],
             data["dense_crlb_pos_rms_um"], data["dense_crlb_rot_rms_urad"]]]
    text = table(["refinement", "pos rms (um)", "rot rms (urad)", "CRLB pos rms", "CRLB rot rms"], rows,
                 f"Dense refinement on the shipped gauge, {data['poses']} poses at 5 um: "
                 f"{data['position_gain']:.2f}x lower position rms than corner-based")
    return text, data


def figure_three(results: list[dict], noises, out) -> tuple[str, dict]:
    mine = [r for r in results if r["n"] == 5]
    rows, data = [], {}
    for noise in noises:
        stack = np.concatenate([r["rows"][noise] for r in mine]) * 1e6
        entry = {}
        for key in ("cf_reproj", "ref_reproj", "cf_pos", "ref_pos"):
            v = stack[:, COLUMNS.index(key)]
            v = v[np.isfinite(v)]
            entry[key] = {"mean": float(v.mean()), "std": float(v.std())}
        data[f"{noise * 1e6:g} um"] = entry
        rows.append([f"{noise * 1e6:g}", entry["cf_reproj"]["mean"], entry["cf_reproj"]["std"],
                     entry["ref_reproj"]["mean"], entry["ref_reproj"]["std"], entry["cf_pos"]["mean"],
                     entry["ref_pos"]["mean"]])
    text = table(["noise (um)", "CF mean", "CF std", "CF-Opt mean", "CF-Opt std", "CF pos mean", "CF-Opt pos mean"],
                 rows, f"Fig. 3: n = 5, {len(mine)} gauges: reprojection error (um) and true position error (um)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [noise * 1e6 for noise in noises]
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, (key, title) in zip(axes, (("cf_reproj", "(a) CF reprojection error"),
                                        ("ref_reproj", "(b) CF-Opt reprojection error"),
                                        ("ref_pos", "(c) CF-Opt true position error"))):
        means = [data[f"{v:g} um"][key]["mean"] for v in x]
        stds = [data[f"{v:g} um"][key]["std"] for v in x]
        ax.errorbar(x, means, yerr=stds, marker="o", capsize=3)
        ax.set_title(title)
        ax.set_xlabel("noise (um)")
        ax.set_ylabel("um")
        ax.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / "fig3_noise.png", dpi=120)
    plt.close(figure)
    return text, data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n = 4, 5; 4 gauges x 5 poses; 4 noise levels")
    parser.add_argument("--no-dense-bound", action="store_true", help="skip the dense CRLB (slowest part)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    if args.quick:
        ns, ms, poses, noises, dense_poses = (4, 5), (2, 4), 5, [0.0, 5e-6, 25e-6, 45e-6], 20
    else:
        ns, ms, poses, noises, dense_poses = (4, 5, 7, 10), (10, 50, 100, 150), 100, [k * 5e-6 for k in range(10)], 1000
    tasks = [(n, args.seed * 1000 + 17 * n + k, poses, noises if n == 5 else [TABLE_NOISE], not args.no_dense_bound)
             for n in ns for k in range(max(ms))]
    out = run_dir(args.out, "study")
    from tqdm import tqdm

    dense_tasks = [(args.seed * 7919 + k, dense_poses // 10) for k in range(10)]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        results = list(tqdm(pool.map(gauge_trial, tasks), total=len(tasks), desc="gauges", file=sys.stderr))
        dense_chunks = list(tqdm(pool.map(dense_trial, dense_tasks), total=len(dense_tasks), desc="dense",
                                 file=sys.stderr))
    paper, extra, table_data = table_one(results, ns, ms)
    outliers, outlier_data = outlier_table(results)
    dense, dense_data = dense_table(dense_chunks)
    fig_text, fig_data = figure_three(results, noises, out)
    print(paper, extra, outliers, dense, fig_text, sep="\n\n")
    write_json(out / "study.json", {"table_one": table_data, "outliers": outlier_data, "dense": dense_data,
                                    "figure_three": fig_data, "poses_per_gauge": poses})
    print(f"\nresults: {out / 'study.json'}, {out / 'fig3_noise.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
