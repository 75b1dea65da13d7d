"""profile_pose calibration-study: profile_pose_calibrate on sim_cells whose gauge and profiler sit where the
loop's nodes do not know (random hidden placements), each calibration compared with the simulator's truth.

Each placement is a fresh graph: sim_cell with the hidden truth, profiler_driver, pose_estimator and
motoplus_bridge in calibration mode; the calibration runs through them as on a real cell. Prints one row per
placement (errors, their ratio to the reported standard deviations, the robot's motion time) and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from ..core.commissioning.hand_eye import X_ROTATION, X_TRANSLATION, Y_ROTATION, Y_TRANSLATION, Bounds
from ..core.model.transform import Transform, difference
from . import processes
from .graph import Graph, free_ports
from .report import run_dir, table, write_json

# The range: gauge turned up to 30 deg about base z and 5 deg about x and y, offset up to 50 mm; the
# profiler offset up to 30 mm on the flange and tilted up to 5 deg
GAUGE_TURN = np.radians([5.0, 5.0, 30.0])
GAUGE_OFFSET = 0.05
PROFILER_TILT = np.radians([5.0, 5.0, 5.0])
PROFILER_OFFSET = 0.03


def hidden_placement(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(gauge_in_base, profiler_in_flange) as sim_cell parameters, uniform over the ranges above."""
    gauge = np.r_[rng.uniform(-GAUGE_OFFSET, GAUGE_OFFSET, 3), rng.uniform(-1.0, 1.0, 3) * GAUGE_TURN]
    profiler = np.r_[rng.uniform(-PROFILER_OFFSET, PROFILER_OFFSET, 3), rng.uniform(-1.0, 1.0, 3) * PROFILER_TILT]
    return gauge, profiler


def start_cell(graph: Graph, gauge_in_base, profiler_in_flange, gauge_file: str = "", seed: int = 0,
               rate_hz: float = 83.333) -> dict:
    """sim_cell with the hidden truth, the driver and the estimator; returns the bridge's parameters (the
    bridge and the compensator are the caller's)."""
    period = 0.012 if rate_hz < 200 else 0.004
    ports = dict(zip(("profiler", "mcu", "robot"), free_ports(3)))
    gauge = {"gauge_file": gauge_file} if gauge_file else {}
    graph.start("sim_cell", {"profiler_port": ports["profiler"], "mcu_port": ports["mcu"], "robot_port": ports["robot"],
                             "control_period": period, "seed": seed,
                             "gauge_in_base": [float(v) for v in gauge_in_base],
                             "profiler_in_flange": [float(v) for v in profiler_in_flange], **gauge})
    graph.start("profiler_driver", {"port": ports["profiler"], "serial_url": f"socket://127.0.0.1:{ports['mcu']}"})
    graph.start("pose_estimator", {"refine_model": "dense", **gauge})
    return {"port": ports["robot"], "period": period}


def calibrated(graph: Graph, bridge: dict, out: Path) -> dict:
    """Run profile_pose_calibrate on a graph whose cell, driver and estimator run: the bridge started in
    calibration mode for it and stopped after. Returns the compensator's parameters (gauge_in_base,
    profiler_in_tool); raises RuntimeError, with the reason, when the calibration is refused."""
    report, problem = calibration_on(graph, bridge, out)
    if problem:
        raise RuntimeError(f"calibration refused: {problem}")
    return {"gauge_in_base": report["gauge_in_base"], "profiler_in_tool": report["profiler_in_tool"]}


def calibration_on(graph: Graph, bridge: dict, out: Path,
                   robot_sigma: tuple[float, float] = (Bounds.robot_translation_sigma, Bounds.robot_rotation_sigma)
                   ) -> tuple[dict | None, str]:
    """profile_pose_calibrate as a user runs it, its own process, on a running cell, driver and estimator;
    its files go to `out`. Returns its report (None when it wrote none) and what went wrong ("" if nothing)."""
    graph.start("motoplus_bridge", {**bridge, "mode": "calibration"})
    command = processes.executable("profile_pose_calibrate", "profile_pose_ros.nodes.calibrate") + [
        "--out", str(out), "--yes", "--wait", "90", "--robot-sigma", *map(str, robot_sigma)]
    if graph.namespace:
        command += ["--ros-args", "-r", f"__ns:=/{graph.namespace}"]
    try:
        done = subprocess.run(command, env=dict(os.environ, ROS_DOMAIN_ID=str(graph.domain_id)),
                              stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300)
    finally:
        graph.stop("motoplus_bridge")
    (out / "calibrate.log").write_text(done.stdout + done.stderr)
    report_file = out / "calibration.json"
    report = json.loads(report_file.read_text()) if report_file.exists() else None
    problem = "" if done.returncode == 0 else (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
    return report, problem


def errors(report: dict, gauge_in_base, profiler_in_flange) -> dict:
    """Calibration minus truth, in the calibration's own terms, and each component over its std."""
    truth = np.r_[difference(Transform.from_vector(profiler_in_flange), Transform.from_vector(report["profiler_in_tool"])),
                  difference(Transform.from_vector(gauge_in_base), Transform.from_vector(report["gauge_in_base"]))]
    sigma = np.sqrt(np.diag(report["covariance"]))
    ratio = np.abs(truth) / sigma
    return {"profiler_rotation_mrad": float(np.linalg.norm(truth[X_ROTATION]) * 1e3),
            "profiler_translation_mm": float(np.linalg.norm(truth[X_TRANSLATION]) * 1e3),
            "gauge_rotation_mrad": float(np.linalg.norm(truth[Y_ROTATION]) * 1e3),
            "gauge_translation_mm": float(np.linalg.norm(truth[Y_TRANSLATION]) * 1e3),
            "max_error_over_sigma": float(ratio.max()), "rms_error_over_sigma": float(np.sqrt(np.mean(ratio ** 2))),
            "error": truth.tolist(), "sigma": sigma.tolist()}


def calibrate_hidden(out: Path, gauge_in_base, profiler_in_flange, gauge_file: str = "", seed: int = 0,
                     rate_hz: float = 83.333, robot_sigma: tuple[float, float] = (Bounds.robot_translation_sigma,
                                                                                 Bounds.robot_rotation_sigma)):
    """One calibration on a fresh sim_cell graph: (its report or None, what went wrong)."""
    graph = Graph(out / "logs", client_name="calibration_study")
    try:
        bridge = start_cell(graph, gauge_in_base, profiler_in_flange, gauge_file, seed, rate_hz)
        return calibration_on(graph, bridge, out, robot_sigma=robot_sigma)
    finally:
        graph.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--gauge", default="config/gauge_designed_n6.yaml")
    parser.add_argument("--rate", type=float, default=83.333, help="controller rate (Hz)")
    parser.add_argument("--robot-sigma", type=float, nargs=2, default=[Bounds.robot_translation_sigma,
                                                                       Bounds.robot_rotation_sigma],
                        help="the controller's pose noise the calibration assumes (m, rad); sim_cell's controller "
                             "reports its pose to 1 um and 0.0001 deg (0.3 um and 1 urad std)")
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "calibration_study")
    rng = np.random.default_rng(args.seed)
    rows, results = [], []
    for k in range(args.placements):
        gauge_in_base, profiler_in_flange = hidden_placement(rng)
        report, problem = calibrate_hidden(out / f"placement{k}", gauge_in_base, profiler_in_flange, args.gauge,
                                           seed=args.seed * 1000 + k, rate_hz=args.rate,
                                           robot_sigma=tuple(args.robot_sigma))
        entry = {"placement": k, "gauge_in_base": gauge_in_base.tolist(),
                 "profiler_in_flange": profiler_in_flange.tolist(), "problem": problem}
        if report is not None:
            entry.update(errors(report, gauge_in_base, profiler_in_flange), chi2=report["chi2"], dof=report["dof"],
                         robot_motion_s=report["robot_motion_s"])
        results.append(entry)
        row = [str(k), f"{np.degrees(gauge_in_base[5]):+.1f}", f"{np.linalg.norm(profiler_in_flange[:3]) * 1e3:.1f}"]
        if report is None:
            row += ["-"] * 5 + [problem[:60]]
        else:
            row += [f"{entry['gauge_rotation_mrad']:.3f}", f"{entry['profiler_rotation_mrad']:.3f}",
                    f"{entry['profiler_translation_mm']:.3f}", f"{entry['max_error_over_sigma']:.2f}",
                    f"{report['chi2']:.0f}/{report['dof']}", problem[:60] or "ok"]
        rows.append(row)
        print(f"placement {k}: {row}", flush=True)
    print(table(["#", "gauge rz (deg)", "profiler offset (mm)", "gauge rot err (mrad)", "profiler rot err (mrad)",
                 "profiler pos err (mm)", "max err/std", "chi2/dof", "verdict"], rows))
    ok = [r for r in results if not r["problem"]]
    if ok:
        print(f"{len(ok)} of {len(results)} calibrated; worst: gauge rotation {max(r['gauge_rotation_mrad'] for r in ok):.3f} "
              f"mrad, profiler rotation {max(r['profiler_rotation_mrad'] for r in ok):.3f} mrad, profiler translation "
              f"{max(r['profiler_translation_mm'] for r in ok):.3f} mm, error/std {max(r['max_error_over_sigma'] for r in ok):.2f} "
              f"(rms over all {np.sqrt(np.mean([r['rms_error_over_sigma'] ** 2 for r in ok])):.2f}: 1 when the "
              "reported deviations are honest, below 1 when conservative); "
              f"robot motion {ok[0]['robot_motion_s']:.1f} s per calibration")
    write_json(out / "calibration_study.json", {"seed": args.seed, "gauge": args.gauge, "placements": results})
    print(f"results: {out / 'calibration_study.json'}")
    return 0 if len(ok) == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
