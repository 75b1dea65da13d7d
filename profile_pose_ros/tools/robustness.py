"""profile_pose robustness: the estimator on profiles that are not clean — spikes, gaps, noise well above
the profiler's — per gauge family: how often it refuses (and why), how often an accepted pose is wrong,
whether its covariance is honest (NEES), and what each profile costs.

A pose counts as wrong when it is more than 1 mm or 5 mrad off; as overconfident when its NEES against the
truth is beyond the chi-square(6) 99.9 % quantile *and* its position is more than 0.1 mm off: a large error
the covariance does not own. Gaps are 10 % of the lit
span, centred on a corner (over) or half-way between two (between). Both cores are used; --quick is the
test's reduced run.

--bound asks, of every refused profile, what the best possible estimator could have done with it: the dense
Cramér-Rao bound at the true pose for the points the profile has, whether its position std exceeds the
estimator's gate (then no estimator determines the view well enough to pass it), and the chance that an
estimator reaching the bound would have been wrong had it published the pose (a Gaussian at the bound).
Refusals beyond the bound are the view's, not the estimator's; publishing them costs that many wrong poses.

--gates asks what the estimator's precision gate (max_position_sigma) trades: the run publishes every pose
the estimator can (its gate opened), the main table still judges each by the configured gate, and a second
table gives, for each candidate gate, the worst refusal rate among the cells at the profiler's own noise, the
wrong poses published and the wrong poses the published poses' covariances predict; a third, NEES by the
position std each pose claimed: whether the covariance stays honest beyond the gate. A commissioning engineer
can run it on the cell's own gauge file before choosing a gate.

Every cell also says how many wrong poses its accepted poses' own covariances predict (the chance each has
of being wrong, were its error the Gaussian its covariance describes, summed): an estimator whose covariance
is honest publishes about that many, and no gate above the poses' σ removes them.

--repeats K times each profile K times: the first call's time is the one a node sees, a new profile's cold
caches and branch predictors and the machine's jitter included (on a busy 2-core machine it doubles a cell's
p99); the fastest of the K, reported beside it, is the estimator's cost with all of that warm from the same
profile: a lower bound, which tells the estimator's own slow paths from the machine.
"""
from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import re
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache

import numpy as np

from ..core import estimate_pose, pose_error, render_profile, sample_pose
from ..core.compiled.render_kernel import trace_depth_fast
from ..core.design.crlb import dense_crlb_of_points
from ..core.design.gauge_design import random_gauge
from ..core.estimation.estimator import pose_nees, warm_up
from ..core.estimation.result import REFINE_MODELS, EstimatorOptions, position_sigma, reason_poorly_determined
from ..core.model.gauge import Gauge
from ..core.model.render import true_corners
from ..resources import config_path
from .report import run_dir, summary, table, write_json

NEES_999 = 22.458  # chi-square, 6 degrees of freedom, 99.9 %
NEES_99 = 16.812  # and 99 %
WRONG_POSITION, WRONG_ROTATION = 1e-3, 5e-3  # m, rad
OVERCONFIDENT_POSITION = 1e-4  # m
GAP_FRACTION = 0.10
BASE_NOISE = 5e-6

# the gauges a run covers by default: the shipped ones, and random ones of 4-10 ridges
FAMILIES = ("gauge_paper_n5.yaml", "gauge_designed_n6.yaml", "random n=4", "random n=5", "random n=7", "random n=10")
# condition -> (noise, spike fraction, gap placement)
CONDITIONS = {
    "clean": (BASE_NOISE, 0.0, None),
    "spikes 0.5 %": (BASE_NOISE, 0.005, None),
    "spikes 1 %": (BASE_NOISE, 0.01, None),
    "spikes 2 %": (BASE_NOISE, 0.02, None),
    "spikes 5 %": (BASE_NOISE, 0.05, None),
    "gap over a corner": (BASE_NOISE, 0.0, "over"),
    "gap between corners": (BASE_NOISE, 0.0, "between"),
    "noise 15 um": (15e-6, 0.0, None),
    "noise 25 um": (25e-6, 0.0, None),
    "noise 45 um": (45e-6, 0.0, None),
}
# glints as a specular face gives them, a few pixels side by side: condition -> share of the points, at BASE_NOISE.
# Drawn from a generator of their own, so that adding them left every cell above with the profiles it had
GLINT_CONDITIONS = {"glints 2 % (runs of 3-8)": 0.02, "glints 5 % (runs of 3-8)": 0.05}
GLINT_RUN = (3, 8)  # points a glint lights, fewest and most


def _family_index(family: str, families: list[str]) -> int:
    """Which seed offset a family's profiles draw from: its place in the default list, so that a run of a few
    families (--families "random n=5") sees the very profiles the full run at that seed does; others after."""
    if family in FAMILIES:
        return FAMILIES.index(family)
    return len(FAMILIES) + [f for f in families if f not in FAMILIES].index(family)


def family_gauges(family: str, count: int, seed: int) -> list[Gauge]:
    if family.startswith("random n="):
        rng = np.random.default_rng(seed)
        return [random_gauge(int(family.split("=")[1]), rng) for _ in range(count)]
    return [Gauge.from_yaml(config_path(family))]


def with_gap(points: np.ndarray, corners_x: np.ndarray, placement: str, rng: np.random.Generator) -> np.ndarray:
    """points with 10 % of the lit span removed, centred on a corner or between two."""
    lit = points[np.isfinite(points[:, 1]), 0]
    width = GAP_FRACTION * (lit.max() - lit.min())
    inside = np.sort(corners_x[(corners_x > lit.min()) & (corners_x < lit.max())])
    if placement == "over" or len(inside) < 2:
        centre = rng.choice(inside) if len(inside) else 0.5 * (lit.min() + lit.max())
    else:
        k = rng.integers(len(inside) - 1)
        centre = 0.5 * (inside[k] + inside[k + 1])
    gapped = points.copy()
    gapped[np.abs(points[:, 0] - centre) < width / 2, 1] = np.nan
    return gapped


def with_glints(points: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """points with glints on about `fraction` of the valid ones: runs of GLINT_RUN points side by side, each run
    off the face by one height (0.2-2 mm, either way, as render_profile's spikes) shaped as a peak (half of it
    at the run's ends), each point within 20 % of its share."""
    glinted = points.copy()
    valid = np.flatnonzero(np.isfinite(points[:, 1]))
    budget = int(round(fraction * len(valid)))
    while budget > 0 and len(valid):
        start = int(rng.integers(len(valid)))
        run = valid[start:start + int(rng.integers(GLINT_RUN[0], GLINT_RUN[1] + 1))]
        peak = 0.5 + 0.5 * np.sin(np.pi * np.arange(1, len(run) + 1) / (len(run) + 1))
        glinted[run, 1] += (rng.choice([-1.0, 1.0]) * rng.uniform(2e-4, 2e-3) * peak *
                            rng.uniform(0.8, 1.2, len(run)))
        budget -= len(run)
    return glinted


def condition_noise(condition: str) -> float:
    """The depth noise a condition's profiles have (m)."""
    return BASE_NOISE if condition in GLINT_CONDITIONS else CONDITIONS[condition][0]


def wrong_if_published(covariance: np.ndarray, draws: int = 20000, rng: np.random.Generator | None = None) -> float:
    """The chance that a pose with this (ROS-order) error covariance is wrong: more than WRONG_POSITION or
    WRONG_ROTATION off. Drawn from rng, or without one from the same draws every time (a run repeats either
    way; a sum over many poses wants rng, whose draws differ from pose to pose)."""
    values, vectors = np.linalg.eigh(covariance)
    standard = _standard_draws(draws) if rng is None else rng.standard_normal((draws, 6))
    # einsum, not @: a matrix product would wake BLAS threads onto the cores another worker is timing on
    errors = np.einsum("dk,jk->dj", standard, vectors * np.sqrt(np.clip(values, 0.0, None)))
    return float(((np.linalg.norm(errors[:, :3], axis=1) > WRONG_POSITION) |
                  (np.linalg.norm(errors[:, 3:], axis=1) > WRONG_ROTATION)).mean())


@lru_cache(maxsize=2)
def _standard_draws(draws: int) -> np.ndarray:
    return np.random.default_rng(0).standard_normal((draws, 6))


def may_be_wrong(covariance: np.ndarray) -> bool:
    """Whether a pose with this (ROS-order) covariance has a chance of being wrong worth drawing for: beyond
    WRONG_POSITION and WRONG_ROTATION lie over 6.5 of its largest standard deviations otherwise (a chance under
    1e-8)."""
    return bool(np.linalg.eigvalsh(covariance[:3, :3]).max() > (WRONG_POSITION / 6.5) ** 2 or
                np.linalg.eigvalsh(covariance[3:, 3:]).max() > (WRONG_ROTATION / 6.5) ** 2)


def family_trial(task: tuple) -> list[dict]:
    """Every condition on the same poses of one gauge: one record per profile. judged_gate (m, or None): the
    precision gate each record's "ok" is judged by when the estimator ran with its own gate opened (--gates);
    "published" says what that estimator published."""
    family, gauge_index, seed, poses, overrides, bound, repeats, judged_gate = task
    gauge = family_gauges(family, gauge_index + 1, seed)[gauge_index]
    rng = np.random.default_rng(seed * 7919 + gauge_index)
    options = EstimatorOptions().with_changes(**overrides)  # once, as a node holds them
    judged = None if judged_gate is None else options.with_changes(max_position_sigma=judged_gate)
    warm_up(gauge, options)  # the kernels loaded (or built) before the first timed profile
    glint_rng = np.random.default_rng(seed * 7919 + gauge_index + 2)
    records, unbounded, uncertain = [], [], []
    for _ in range(poses):
        rotation, t = sample_pose(gauge, rng, trace=trace_depth_fast)
        corners_x = true_corners(gauge, rotation, t)[:, 0]
        for condition, points, noise in _profiles(gauge, rotation, t, corners_x, rng, glint_rng):
            start = time.perf_counter()
            estimate = estimate_pose(points, gauge, options)
            elapsed = fastest = time.perf_counter() - start
            for _ in range(repeats - 1):  # the same answer again: only its time differs (warm caches, jitter)
                start = time.perf_counter()
                estimate_pose(points, gauge, options)
                fastest = min(fastest, time.perf_counter() - start)
            record = {"condition": condition, "ok": estimate.ok, "published": estimate.ok, "reason": estimate.reason,
                      "time": elapsed, "fastest": fastest}
            if estimate.ok:
                position, rotation_error = pose_error(estimate.R, estimate.t, rotation, t)
                record.update(position=position, rotation=rotation_error, nees=pose_nees(estimate, rotation, t),
                              sigma=estimate.position_sigma, wrong_expected=0.0)
                if may_be_wrong(estimate.covariance):
                    uncertain.append((record, estimate.covariance))
                if judged is not None and estimate.position_sigma > judged.max_position_sigma:
                    record.update(ok=False, reason=reason_poorly_determined(estimate.position_sigma, judged))
            if bound and not record["ok"]:
                unbounded.append((record, points, rotation, t, noise))
            records.append(record)
    draws = np.random.default_rng(seed * 7919 + gauge_index + 1)
    for record, covariance in uncertain:  # summed over a cell: fewer draws a pose, independent ones
        record["wrong_expected"] = wrong_if_published(covariance, draws=4000, rng=draws)
    # after every timed estimate: the bound's linear algebra wakes BLAS threads that would share the core
    for record, points, rotation, t, noise in unbounded:
        crlb = dense_crlb_of_points(gauge, points, rotation, t, noise)
        record.update(crlb_sigma=position_sigma(crlb[:3, :3]), wrong_if_published=wrong_if_published(crlb))
    return records


def _profiles(gauge: Gauge, rotation: np.ndarray, t: np.ndarray, corners_x: np.ndarray, rng: np.random.Generator,
              glint_rng: np.random.Generator):
    """(condition, points, noise) for every condition at one pose, each rendered just before its estimate."""
    for condition, (noise, spikes, gap) in CONDITIONS.items():
        points = render_profile(gauge, rotation, t, noise_std=noise, rng=rng, spike_fraction=spikes,
                                trace=trace_depth_fast)
        yield condition, with_gap(points, corners_x, gap, rng) if gap else points, noise
    for condition, fraction in GLINT_CONDITIONS.items():
        points = render_profile(gauge, rotation, t, noise_std=BASE_NOISE, rng=glint_rng, trace=trace_depth_fast)
        yield condition, with_glints(points, fraction, glint_rng), BASE_NOISE


def reason_kind(reason: str) -> str:
    """A refusal's words with its numbers taken out, so that alike refusals count together."""
    return re.sub(r"-?\d+(\.\d+)?", "#", reason)


def cell(records: list[dict], gate: float) -> dict:
    """One cell's figures; gate: the estimator's max_position_sigma (m), for the --bound readout."""
    accepted = [r for r in records if r["ok"]]
    bounded = [r for r in records if "crlb_sigma" in r]
    wrong = [r for r in accepted if r["position"] > WRONG_POSITION or r["rotation"] > WRONG_ROTATION]
    overconfident = [r for r in accepted if r["nees"] > NEES_999 and r["position"] > OVERCONFIDENT_POSITION]
    reasons = Counter(reason_kind(r["reason"]) for r in records if not r["ok"])
    nees = np.array([r["nees"] for r in accepted])
    return {"profiles": len(records), "refused_pct": 100.0 * (1 - len(accepted) / max(len(records), 1)),
            "wrong_pct": 100.0 * len(wrong) / max(len(records), 1), "wrong": len(wrong),
            "wrong_expected": sum(r["wrong_expected"] for r in accepted),
            "worst_wrong_position_mm": max((r["position"] * 1e3 for r in wrong), default=0.0),
            "overconfident_pct": 100.0 * len(overconfident) / max(len(records), 1),
            "nees_beyond_99_pct": 100.0 * float((nees > NEES_99).mean()) if nees.size else float("nan"),
            "nees_mean": float(nees.mean()) if nees.size else float("nan"),
            "nees_beyond_999_pct": 100.0 * float((nees > NEES_999).mean()) if nees.size else float("nan"),
            "time_ms": summary(1e3 * np.array([r["time"] for r in records])),
            "fastest_ms": summary(1e3 * np.array([r["fastest"] for r in records])),
            "top_refusal": reasons.most_common(1)[0][0] if reasons else "",
            "refusals": dict(reasons.most_common(5)),
            **({"refused_beyond_bound_pct": 100.0 * sum(r["crlb_sigma"] > gate for r in bounded) / len(records),
                "wrong_if_refused_published": sum(r["wrong_if_published"] for r in bounded)} if bounded else {})}


def gate_frontier(by_cell: dict[tuple[str, str], list[dict]], gates: list[float]) -> list[dict]:
    """What each candidate precision gate (m) would have published of a run made with the gate opened: per gate,
    the worst cell's refusal rate among the cells at the profiler's own noise (the noise sweep's refusals are
    the gate's purpose), the wrong poses published and those the published poses' covariances predict."""
    base = {key: records for key, records in by_cell.items() if condition_noise(key[1]) == BASE_NOISE}
    everything = [r for records in by_cell.values() for r in records]
    rows = []
    for gate in gates:
        def kept(r: dict) -> bool:
            return r["published"] and r["sigma"] <= gate
        refused = {key: 100.0 * sum(not kept(r) for r in records) / len(records) for key, records in base.items()}
        worst = max(refused, key=refused.get) if refused else None
        published = [r for r in everything if kept(r)]
        rows.append({"gate_mm": gate * 1e3, "profiles": len(everything), "accepted": len(published),
                     "worst_refused_pct": refused[worst] if worst else float("nan"),
                     "worst_cell": " | ".join(worst) if worst else "",
                     "wrong": sum(r["position"] > WRONG_POSITION or r["rotation"] > WRONG_ROTATION for r in published),
                     "wrong_expected": sum(r["wrong_expected"] for r in published)})
    return rows


def nees_by_sigma(records: list[dict], edges: list[float]) -> list[dict]:
    """NEES of the published poses by the position std they claimed, in bands between edges (m): an honest
    covariance reads about 6 in every band, so where it stops being honest shows as the band it rises in."""
    published = [r for r in records if r["published"]]
    rows = []
    for low, high in zip(edges[:-1], edges[1:]):
        nees = np.array([r["nees"] for r in published if low < r["sigma"] <= high])
        rows.append({"sigma_mm": [low * 1e3, high * 1e3], "poses": int(nees.size),
                     "nees_mean": float(nees.mean()) if nees.size else float("nan"),
                     "nees_beyond_99_pct": 100.0 * float((nees > NEES_99).mean()) if nees.size else float("nan")})
    return rows


def _option(item: str) -> tuple[str, object]:
    """OPTION=VALUE as the estimator takes it (YAML's reading of VALUE: numbers, true/false, inf)."""
    import yaml

    name, _, text = item.partition("=")
    value = yaml.safe_load(text)
    if isinstance(value, str):  # YAML 1.1 reads 3e-4 (no dot) and inf as strings
        try:
            value = float(text)
        except ValueError:
            pass
    return name, value


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 gauges per random family, 6 poses each")
    parser.add_argument("--families", nargs="+", default=list(FAMILIES))
    parser.add_argument("--gauges", type=int, default=10, help="random gauges per random family")
    parser.add_argument("--poses", type=int, default=20, help="poses per gauge (shipped gauges: x gauges)")
    parser.add_argument("--refine-model", default="auto", choices=REFINE_MODELS,
                        help="the estimator's default and the node's: auto (corners: the paper's model alone)")
    parser.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                        help="estimator options (pose_estimator's parameter names), e.g. spike_threshold=0 "
                             "max_residual_ratio=inf for the estimator without its spike filter and consistency test")
    parser.add_argument("--bound", action="store_true",
                        help="for every refused profile, the dense Cramer-Rao bound at the truth: how many refusals "
                             "no estimator could have passed the gate with, and the wrong poses publishing them "
                             "would cost an estimator at the bound")
    parser.add_argument("--gates", nargs="+", type=float, default=[], metavar="MM",
                        help="candidate precision gates (max_position_sigma, mm): run with the estimator's gate "
                             "opened and report what each would refuse, publish wrong and predict wrong, and the NEES "
                             "by claimed position std (the main table still judges by the configured gate)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="time each profile this many times: the first call's time stays the one reported "
                             "(what a node sees), the fastest is reported beside it (the estimator's own cost with "
                             "warm caches: a lower bound)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if any(not gate > 0 for gate in args.gates):
        parser.error("--gates must be positive (mm)")
    gauges, poses = (2, 6) if args.quick else (args.gauges, args.poses)
    options = {"refine_model": args.refine_model, **dict(_option(item) for item in args.set)}
    gate = EstimatorOptions().with_changes(**options).max_position_sigma
    judged_gate = gate if args.gates else None
    run_options = {**options, "max_position_sigma": math.inf} if args.gates else options
    tasks = []
    for family in args.families:
        f = _family_index(family, args.families)
        if family.startswith("random n="):
            tasks += [(family, k, args.seed + 101 * f, poses, run_options, args.bound, args.repeats, judged_gate)
                      for k in range(gauges)]
        else:  # one shipped gauge, as many poses as a random family has
            tasks += [(family, 0, args.seed + 101 * f + k, poses, run_options, args.bound, args.repeats,
                       judged_gate) for k in range(gauges)]
    from tqdm import tqdm

    context = None
    if args.bound:  # the bound's matrix products would wake BLAS threads that spin on the cores being timed
        os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        context = multiprocessing.get_context("spawn")  # workers that import numpy under those settings
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=context) as pool:
        results = list(tqdm(pool.map(family_trial, tasks), total=len(tasks), desc="gauges", file=sys.stderr))
    by_cell: dict[tuple[str, str], list[dict]] = {}
    for task, records in zip(tasks, results):
        for record in records:
            by_cell.setdefault((task[0], record["condition"]), []).append(record)
    cells = {f"{family} | {condition}": cell(records, gate) for (family, condition), records in by_cell.items()}
    rows = [[name.split(" | ")[0].replace(".yaml", ""), name.split(" | ")[1], str(c["profiles"]),
             f"{c['refused_pct']:.1f}", f"{c['wrong']} / {c['wrong_expected']:.2f}", f"{c['overconfident_pct']:.1f}",
             f"{c['nees_mean']:.1f}", f"{c['nees_beyond_99_pct']:.1f}", f"{c['time_ms']['median']:.3f}",
             f"{c['time_ms']['p99']:.2f}", *([f"{c['fastest_ms']['p99']:.2f}"] if args.repeats > 1 else []),
             *([f"{c.get('refused_beyond_bound_pct', 0.0):.1f}", f"{c.get('wrong_if_refused_published', 0.0):.1f}"]
               if args.bound else []),
             c["top_refusal"][:70]] for name, c in cells.items()]
    bound_headers = ["refused beyond bound %", "wrong if published"] if args.bound else []
    fastest_headers = [f"ms p99, fastest of {args.repeats}"] if args.repeats > 1 else []
    print(table(["gauge", "condition", "profiles", "refused %", "wrong / expected", "overconf. %", "NEES",
                 "NEES>16.8 %", "ms p50", "ms p99", *fastest_headers, *bound_headers, "most common refusal"], rows,
                title=f"The estimator on unclean profiles ({args.refine_model} refinement; wrong = more than "
                      f"{WRONG_POSITION * 1e3:g} mm or {WRONG_ROTATION * 1e3:g} mrad off; overconfident = NEES "
                      f"beyond {NEES_999} and > {OVERCONFIDENT_POSITION * 1e3:g} mm off)"))
    accepted = sum(c["profiles"] * (1 - c["refused_pct"] / 100) for c in cells.values())
    wrong = sum(c["profiles"] * c["wrong_pct"] / 100 for c in cells.values())
    expected = sum(c["wrong_expected"] for c in cells.values())
    print(f"\n{sum(c['profiles'] for c in cells.values())} profiles, {accepted:.0f} accepted, {wrong:.0f} wrong "
          f"({expected:.1f} expected from the accepted poses' own covariances)")
    report = {"options": options, "cells": cells}
    if args.gates:
        report.update(print_gates(by_cell, sorted(g * 1e-3 for g in args.gates), gate))
    out = run_dir(args.out, "robustness")
    write_json(out / "robustness.json", report)
    print(f"\nresults: {out / 'robustness.json'}")
    return 0


def print_gates(by_cell: dict[tuple[str, str], list[dict]], gates: list[float], configured: float) -> dict:
    """--gates' two tables, printed; their rows for the report."""
    frontier = gate_frontier(by_cell, gates)
    per_5000 = 5000.0 / max(frontier[0]["profiles"], 1)
    print(table(["gate (mm)", "accepted", "worst refused % at base noise", "in", "wrong", "expected",
                 "expected per 5,000"],
                [[f"{row['gate_mm']:.3f}" + (" *" if math.isclose(row["gate_mm"], configured * 1e3) else ""),
                  str(row["accepted"]), f"{row['worst_refused_pct']:.1f}", row["worst_cell"].replace(".yaml", ""),
                  str(row["wrong"]), f"{row['wrong_expected']:.2f}", f"{row['wrong_expected'] * per_5000:.2f}"]
                 for row in frontier],
                title=f"\nWhat the precision gate trades (* the configured {configured * 1e3:g} mm; base noise "
                      f"{BASE_NOISE * 1e6:g} um: every condition but the noise sweep)"))
    bands = nees_by_sigma([r for records in by_cell.values() for r in records], [0.0, *gates, math.inf])
    print(table(["claimed position std (mm)", "poses", "NEES mean", "NEES>16.8 %"],
                [[f"{low:.3f} - {high:.3f}", str(row["poses"]), f"{row['nees_mean']:.2f}",
                  f"{row['nees_beyond_99_pct']:.1f}"] for row in bands for low, high in [row["sigma_mm"]]],
                title="\nNEES of every published pose by the position std it claimed (6 if the covariance is honest)"))
    return {"gates": frontier, "nees_by_sigma": bands}


if __name__ == "__main__":
    sys.exit(main())
