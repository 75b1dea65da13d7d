"""profile_pose gauge: check, design and export gauges before one is machined or printed (paper III-D).

  profile_pose gauge check  GAUGE.yaml   rules, range of motion, occlusion limit, precision (CRLB and
                                         Monte-Carlo) over a required range of motion; table, JSON, plot
  profile_pose gauge design --out NEW.yaml  search gauges minimising the worst CRLB over that range, under
                                         the fabrication rules, against a reference gauge
  profile_pose gauge export GAUGE.yaml --out GAUGE.stl   the solid as a watertight STL (mm)
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..core.model.gauge import Gauge, GaugeError
from ..core.design.gauge_check import (RequiredMotion, check_rules, motion_poses, occlusion_beta_deg, precision_over,
                                       range_of_motion, worst_bound)
from ..core.design.gauge_design import RandomGaugeRules
from ..resources import DEFAULT_GAUGE, config_path
from .report import run_dir, table, write_json

MONTE_CARLO_PROFILES = 200


def add_rule_arguments(parser: argparse.ArgumentParser) -> None:
    rules = RandomGaugeRules()
    parser.add_argument("--max-face-angle", type=float, default=rules.max_face_angle_deg,
                        help="steepest face from horizontal, deg (occlusion: beta = 90 - this)")
    parser.add_argument("--min-face-width", type=float, default=3.5, help="narrowest face at either end, mm")
    parser.add_argument("--min-ridge-separation", type=float, default=rules.min_ridge_separation_deg,
                        help="at least 4 ridge directions this far apart, deg")
    parser.add_argument("--max-relief", type=float, default=rules.max_relief * 1e3, help="mm")
    parser.add_argument("--noise", type=float, default=5.0, help="profiler depth noise, um (1 sigma)")
    parser.add_argument("--standoff", type=float, nargs=2, default=(350.0, 550.0),
                        help="required standoff range to the gauge's mid-height, mm")
    parser.add_argument("--motion-xy", type=float, nargs=2, default=(10.0, 10.0),
                        help="required +- motion along the profiler's x and the gauge's y, mm")
    parser.add_argument("--tilt", type=float, default=10.0, help="required tilt from straight down, deg")
    parser.add_argument("--yaw", type=float, default=10.0, help="required yaw of the laser line, deg")


def rules_from(args) -> RandomGaugeRules:
    return RandomGaugeRules(max_face_angle_deg=args.max_face_angle, min_face_width=args.min_face_width * 1e-3,
                            min_ridge_separation_deg=args.min_ridge_separation, max_relief=args.max_relief * 1e-3)


def motion_from(args) -> RequiredMotion:
    return RequiredMotion(x=args.motion_xy[0] * 1e-3, y=args.motion_xy[1] * 1e-3,
                          standoff=(args.standoff[0] * 1e-3, args.standoff[1] * 1e-3),
                          tilt=np.radians(args.tilt), yaw=np.radians(args.yaw))


def load(path: str) -> Gauge:
    try:
        return Gauge.from_yaml(path)
    except GaugeError as exc:
        raise SystemExit(f"profile_pose gauge: {exc}") from None


def monte_carlo(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, noise: float, seed: int) -> dict:
    """rms position / rotation error of the estimator at one pose over many noisy profiles."""
    from ..core import estimate_pose, pose_error, render_profile

    rng = np.random.default_rng(seed)
    errors, rejected = [], 0
    for _ in range(MONTE_CARLO_PROFILES):
        estimate = estimate_pose(render_profile(gauge, rotation, translation, noise_std=noise, rng=rng), gauge)
        if not estimate.ok:
            rejected += 1
            continue
        errors.append(pose_error(estimate.R, estimate.t, rotation, translation))
    rms = np.sqrt(np.mean(np.square(errors), axis=0)) if errors else np.full(2, np.nan)
    return {"position_rms": float(rms[0]), "rotation_rms": float(rms[1]), "rejected": rejected,
            "profiles": MONTE_CARLO_PROFILES}


def check(args) -> int:
    gauge = load(args.gauge)
    rules, motion, noise = rules_from(args), motion_from(args), args.noise * 1e-6
    out = run_dir(args.out, f"gauge-check-{gauge.name}")
    checks = check_rules(gauge, rules)
    print(table(["rule", "value", "limit", "unit", "result"],
                [[c.rule, f"{c.value:.2f}", f"{c.limit:.2f}", c.unit, "ok" if c.ok else "FAILS"] for c in checks],
                f"Gauge '{gauge.name}' ({args.gauge}): design rules"))
    reach = range_of_motion(gauge)
    beta = occlusion_beta_deg(gauge)
    print(table(["move from the nominal pose", "- side", "+ side", "permissible range"], [
        ["profiler x (mm)", reach.x[0] * 1e3, reach.x[1] * 1e3, reach.span("x") * 1e3],
        ["gauge y (mm)", reach.y[0] * 1e3, reach.y[1] * 1e3, reach.span("y") * 1e3],
        ["profiler z (mm)", reach.z[0] * 1e3, reach.z[1] * 1e3, reach.span("z") * 1e3],
        ["incidence alpha in the laser plane (deg)", np.degrees(reach.alpha[0]), np.degrees(reach.alpha[1]),
         np.degrees(reach.span("alpha"))],
    ], f"Range of motion (Fig. 4a), every corner seen with 1 mm of profile around it; "
       f"occlusion limit beta = {beta:.1f} deg (Fig. 4b)"))
    poses = motion_poses(gauge, motion, thorough=True)
    bounds = precision_over(gauge, poses, noise)
    seen = [b for b in bounds if b.visible]
    worst_position, worst_rotation = worst_bound(bounds)
    order = sorted(range(len(bounds)), key=lambda i: -bounds[i].corner_position if bounds[i].visible else -np.inf)
    chosen = [order[0], order[len(seen) // 2]] if seen else []
    carlo = {i: monte_carlo(gauge, poses[i][1], poses[i][2], noise, args.seed + i) for i in chosen}
    rows = []
    for i in order[:args.rows] + [i for i in chosen if i not in order[:args.rows]]:
        b = bounds[i]
        mc = carlo.get(i)
        rows.append([b.label, b.corner_position * 1e6, b.corner_rotation * 1e6, b.dense_position * 1e6,
                     mc["position_rms"] * 1e6 if mc else "", mc["rotation_rms"] * 1e6 if mc else ""] if b.visible
                    else [b.label, "corner lost", "", "", "", ""])
    print(table(["pose (worst first)", "CRLB pos (um)", "CRLB rot (urad)", "dense CRLB pos (um)",
                 f"MC pos rms ({MONTE_CARLO_PROFILES})", "MC rot rms"], rows,
                f"Precision at {args.noise:g} um over the required motion ({len(poses)} poses, "
                f"{len(poses) - len(seen)} with a corner lost): worst {worst_position * 1e6:.1f} um / "
                f"{worst_rotation * 1e6:.1f} urad"))
    plot_precision(bounds, carlo, out / "precision.png", gauge.name, args.noise)
    failed = [c.rule for c in checks if not c.ok] + (["a corner is lost inside the required motion"]
                                                     if len(seen) < len(poses) else [])
    write_json(out / "check.json", {
        "gauge": args.gauge, "rules": [asdict(c) for c in checks], "range_of_motion": asdict(reach),
        "beta_deg": beta, "noise_m": noise, "motion": asdict(motion),
        "bounds": [asdict(b) for b in bounds], "monte_carlo": {bounds[i].label: v for i, v in carlo.items()},
        "worst_position_m": worst_position, "worst_rotation_rad": worst_rotation, "failed": failed})
    print(f"\n{'VALID' if not failed else 'NOT VALID: ' + '; '.join(failed)}\nresults: {out / 'check.json'}, "
          f"{out / 'precision.png'}")
    return 0 if not failed else 1


def plot_precision(bounds, carlo: dict, path: Path, name: str, noise_um: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    index = np.arange(len(bounds))
    figure, axes = plt.subplots(1, 2, figsize=(12, 3.8))
    for ax, key, unit, mc_key in ((axes[0], "corner_position", "um", "position_rms"),
                                  (axes[1], "corner_rotation", "urad", "rotation_rms")):
        ax.plot(index, [getattr(b, key) * 1e6 for b in bounds], "o-", ms=3, label="corner-model CRLB")
        dense_key = key.replace("corner", "dense")
        ax.plot(index, [getattr(b, dense_key) * 1e6 for b in bounds], "s-", ms=3, label="dense-model CRLB")
        for i, mc in carlo.items():
            ax.plot(i, mc[mc_key] * 1e6, "r*", ms=12, label="Monte-Carlo rms" if i == min(carlo) else None)
        ax.set_xlabel("pose of the required motion")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
        ax.legend()
    axes[0].set_title(f"{name}: position bound at {noise_um:g} um noise")
    axes[1].set_title("rotation bound")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def design(args) -> int:
    from ..core.design.gauge_search import DesignSpace, design_gauge

    reference = load(args.reference)
    rules, motion, noise = rules_from(args), motion_from(args), args.noise * 1e-6
    reference_worst = worst_bound(precision_over(reference, motion_poses(reference, motion), noise, dense=False))
    if not np.isfinite(reference_worst[0]):
        raise SystemExit(f"profile_pose gauge: the reference gauge {args.reference} loses a corner inside the "
                         "required motion; pick a smaller motion or another reference")
    from tqdm import tqdm

    best = None
    for n in args.ridges:
        space = DesignSpace(n, (args.width[0] * 1e-3, args.width[1] * 1e-3), rules, motion, noise, reference_worst,
                            length_range=(args.length[0] * 1e-3, args.length[1] * 1e-3))
        bar = tqdm(total=args.generations, desc=f"n = {n}", file=sys.stderr)

        def step(xk, convergence=None, bar=bar):
            bar.update(1)

        gauge, score, result = design_gauge(space, seed=args.seed, max_generations=args.generations,
                                            population=args.population, workers=args.workers, callback=step)
        bar.close()
        print(f"n = {n}: score {score:.3f} (worst bound / reference's) after {result.nfev} designs")
        if best is None or score < best[1]:
            best = (gauge, score, n)
    gauge, score, n = best
    name = args.name or f"designed_n{n}"
    gauge = Gauge.from_dict({"gauge": dict(gauge.to_dict()["gauge"], name=name)}, source=name)
    thorough = {label: worst_bound(precision_over(g, motion_poses(g, motion, thorough=True), noise, dense=False))
                for label, g in (("reference", reference), ("designed", gauge))}
    ratio = (thorough["reference"][0] / thorough["designed"][0], thorough["reference"][1] / thorough["designed"][1])
    print(table(["gauge", "ridges", "width x length (mm)", "worst CRLB pos (um)", "worst CRLB rot (urad)"], [
        [f"reference {reference.name}", reference.n_ridges, f"{reference.width * 1e3:.0f} x {reference.length * 1e3:.0f}",
         thorough["reference"][0] * 1e6, thorough["reference"][1] * 1e6],
        [f"designed {name}", gauge.n_ridges, f"{gauge.width * 1e3:.1f} x {gauge.length * 1e3:.1f}",
         thorough["designed"][0] * 1e6, thorough["designed"][1] * 1e6],
    ], f"Worst corner-model CRLB over the required motion (80 poses), {args.noise:g} um noise: "
       f"{ratio[0]:.2f}x lower in position, {ratio[1]:.2f}x in rotation"))
    import yaml

    header = (f"# Designed by profile_pose gauge design (seed {args.seed}, {args.generations} generations) against\n"
              f"# {Path(args.reference).name}: worst corner-model CRLB over the required motion at {args.noise:g} um noise\n"
              f"# {thorough['designed'][0] * 1e6:.1f} um / {thorough['designed'][1] * 1e6:.1f} urad "
              f"(reference {thorough['reference'][0] * 1e6:.1f} um / {thorough['reference'][1] * 1e6:.1f} urad).\n"
              f"# Check it with: profile_pose gauge check {args.out}\n")
    Path(args.out).write_text(header + yaml.safe_dump(gauge.to_dict(), sort_keys=False), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


def export(args) -> int:
    from ..core.model.gauge_mesh import export_stl

    gauge = load(args.gauge)
    out = args.out or str(Path(args.gauge).with_suffix(".stl"))
    info = export_stl(gauge, out)
    print(f"wrote {out}: {info['triangles']} triangles, watertight {info['watertight']}, "
          f"{info['volume_cm3']:.1f} cm3, bounds (mm) {info['bounds_mm']}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="profile_pose gauge", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("check", help="validity, range of motion, occlusion, precision")
    p.add_argument("gauge")
    add_rule_arguments(p)
    p.add_argument("--rows", type=int, default=12, help="poses shown in the precision table")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs")
    p.set_defaults(run=check)
    p = commands.add_parser("design", help="search a gauge minimising the worst CRLB")
    add_rule_arguments(p)
    p.add_argument("--out", required=True, help="gauge YAML to write")
    p.add_argument("--name", default="")
    p.add_argument("--reference", default=str(config_path(DEFAULT_GAUGE)), help="the gauge to beat")
    p.add_argument("--ridges", type=int, nargs="+", default=[5, 6, 7])
    p.add_argument("--width", type=float, nargs=2, default=(80.0, 160.0), help="allowed width range, mm")
    p.add_argument("--length", type=float, nargs=2, default=(50.0, 150.0), help="allowed length range, mm")
    p.add_argument("--generations", type=int, default=60)
    p.add_argument("--population", type=int, default=12, help="per parameter (scipy's popsize)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(run=design)
    p = commands.add_parser("export", help="the gauge solid as STL (mm)")
    p.add_argument("gauge")
    p.add_argument("--out", default="")
    p.set_defaults(run=export)
    args = parser.parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
