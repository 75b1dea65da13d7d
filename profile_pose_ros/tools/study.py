"""profile_pose_study: the paper's simulation study (III-B, III-C) with true errors and Cramér-Rao bounds.

Table I: n in {4, 5, 7, 10} ridges x m in {10, 50, 100, 150} random gauges (nested subsets of the same
150) x 100 random poses at 5 um depth noise: mean/std of the reprojection error (eq. 17 as a length) for
the paper's closed form (CF; for n = 4 its minimum-norm solution, as the paper's) and the refined solution
(CF-Opt, for n = 4 started from our null-space candidates), with the paper's notation ('-' when the mean
exceeds 1000 um, '*' below 1 um). Beyond the paper, per n: the true position and rotation errors, the
failure rate, the corner-model and dense-model Cramér-Rao bounds, the estimator's efficiency (rms error /
rms bound) and the NEES of the refined pose against its covariance.
Fig. 3: n = 5, the same 150 gauges x 100 poses at 0, 5, ..., 45 um; printed and plotted against noise.
Both cores are used; --quick gives a reduced run for tests.
"""
from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from ..core import estimate_pose, render_profile, sample_pose
from ..core.crlb import corner_crlb, dense_crlb, position_rotation_rms
from ..core.gauge_design import random_gauge
from ..core.rotation import so3_log
from ..core.solver import paper_closed_form
from .report import run_dir, summary, table, write_json

TABLE_NOISE = 5e-6
FAIL_UM = 1000.0  # the paper's '-' rule


def gauge_trial(task: tuple) -> dict:
    """One random gauge: every pose at every noise level, and the bounds at TABLE_NOISE."""
    n, seed, poses, noises, with_dense = task
    rng = np.random.default_rng(seed)
    gauge = random_gauge(n, rng)
    rows = {noise: [] for noise in noises}
    bounds = []
    for _ in range(poses):
        rotation, t = sample_pose(gauge, rng)
        for noise in noises:
            estimate = estimate_pose(render_profile(gauge, rotation, t, noise_std=noise, rng=rng), gauge,
                                     max_reprojection_error=1.0)
            if not estimate.ok or estimate.closed_form is None:
                rows[noise].append([np.nan] * 7)
                continue
            cf = estimate.closed_form if n > 4 else paper_closed_form(gauge, estimate.corners)
            d = np.concatenate([t - estimate.t, so3_log(rotation @ estimate.R.T)])
            nees = float(d @ np.linalg.solve(estimate.covariance, d)) if noise > 0 else np.nan
            rows[noise].append([cf.reprojection_error, np.linalg.norm(t - cf.translation),
                                np.linalg.norm(so3_log(rotation @ cf.rotation.T)), estimate.reprojection_error,
                                np.linalg.norm(d[:3]), np.linalg.norm(d[3:]), nees])
        if TABLE_NOISE in noises:
            corner = position_rotation_rms(corner_crlb(gauge, rotation, t, TABLE_NOISE))
            dense = position_rotation_rms(dense_crlb(gauge, rotation, t, TABLE_NOISE)) if with_dense else (np.nan,) * 2
            bounds.append([*corner, *dense])
    return {"n": n, "seed": seed, "rows": {noise: np.array(r) for noise, r in rows.items()},
            "bounds": np.array(bounds)}


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
                stack = np.concatenate([r["rows"][TABLE_NOISE] for r in results if r["n"] == n][:m])
                values = stack[:, COLUMNS.index(key)] * 1e6
                cells.append(paper_cell(values))
                data[f"{method} n={n} m={m}"] = summary(values[np.isfinite(values)])
            paper_rows.append([method if n == ns[0] else "", str(n), *cells])
    for n in ns:
        mine = [r for r in results if r["n"] == n][:max(ms)]
        stack = np.concatenate([r["rows"][TABLE_NOISE] for r in mine])
        bounds = np.concatenate([r["bounds"] for r in mine])
        failed = ~np.isfinite(stack[:, 3]) | (stack[:, 3] * 1e6 > FAIL_UM)
        good = stack[~failed]
        rms = lambda col: float(np.sqrt(np.mean(good[:, COLUMNS.index(col)] ** 2)))  # noqa: E731
        corner_pos = float(np.sqrt(np.mean(bounds[:, 0] ** 2)))
        dense_pos = float(np.sqrt(np.nanmean(bounds[:, 2] ** 2)))
        row = {"failure_rate": float(failed.mean()), "ref_pos_rms_um": rms("ref_pos") * 1e6,
               "ref_pos_median_um": float(np.median(good[:, 4])) * 1e6, "ref_rot_rms_urad": rms("ref_rot") * 1e6,
               "cf_pos_median_um": float(np.nanmedian(stack[:, 1])) * 1e6,
               "corner_crlb_pos_rms_um": corner_pos * 1e6, "dense_crlb_pos_rms_um": dense_pos * 1e6,
               "efficiency_pos": rms("ref_pos") / corner_pos, "nees_mean": float(np.nanmean(good[:, 6]))}
        data[f"n={n}"] = row
        extra_rows.append([str(n), f"{100 * row['failure_rate']:.1f} %", row["cf_pos_median_um"],
                           row["ref_pos_median_um"], row["ref_pos_rms_um"], row["ref_rot_rms_urad"],
                           row["corner_crlb_pos_rms_um"], row["dense_crlb_pos_rms_um"], row["efficiency_pos"],
                           row["nees_mean"]])
    paper = table(["", "n", *[f"m = {m}" for m in ms]], paper_rows,
                  "TABLE I: reprojection error mean/std (um), 5 um noise ('-' > 1000 um, '*' < 1 um)")
    extra = table(["n", "failed", "CF pos median (um)", "CF-Opt pos median", "CF-Opt pos rms", "CF-Opt rot rms (urad)",
                   "corner CRLB pos rms", "dense CRLB pos rms", "rms / corner CRLB", "NEES mean (6)"], extra_rows,
                  f"Beyond the paper, m = {max(ms)}: true errors and bounds")
    return paper, extra, data


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
        ns, ms, poses, noises = (4, 5), (2, 4), 5, [0.0, 5e-6, 25e-6, 45e-6]
    else:
        ns, ms, poses, noises = (4, 5, 7, 10), (10, 50, 100, 150), 100, [k * 5e-6 for k in range(10)]
    tasks = [(n, args.seed * 1000 + 17 * n + k, poses, noises if n == 5 else [TABLE_NOISE], not args.no_dense_bound)
             for n in ns for k in range(max(ms))]
    out = run_dir(args.out, "study")
    from tqdm import tqdm

    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        results = list(tqdm(pool.map(gauge_trial, tasks), total=len(tasks), desc="gauges", file=sys.stderr))
    paper, extra, table_data = table_one(results, ns, ms)
    fig_text, fig_data = figure_three(results, noises, out)
    print(paper, extra, fig_text, sep="\n\n")
    write_json(out / "study.json", {"table_one": table_data, "figure_three": fig_data, "poses_per_gauge": poses})
    print(f"\nresults: {out / 'study.json'}, {out / 'fig3_noise.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
