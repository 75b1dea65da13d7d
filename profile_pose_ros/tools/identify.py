"""profile_pose identify: the arm's mode per axis (frequency, damping, gain, delay, with uncertainties)
from small open-loop steps measured by the profiler, for pd_compensator's modal law.

    profile_pose identify                 # on the simulated cell: it steps the robot program itself
    profile_pose identify --bag trial_7   # a real cell: poses recorded while the robot program stepped

On a real cell, record `pose` (bag_recorder) while the robot program makes small fast moves (0.2-0.5 mm,
one axis at a time, at least 1.5 s apart, the bridge disarmed) and give the bag and the step size; the
steps are found in the poses. It writes a parameter file with modal_frequency and modal_damping for
pd_compensator (`--params-file` it after cell.yaml), a JSON report, and a plot of each fit.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

from ..core.control.mode_identification import ModeFit, combine, fit_step, step_response
from .report import run_dir, table, write_json

AXES = ("x", "y", "z")
RECORD_S = 1.5  # after each step: the y mode (damping ~0.02) still rings then, but 15 cycles pin it down
REST_BEFORE_S = 0.2
STEP_SHARE = 0.5  # a step is found where the pose passes half the given size from where it rested
# A recorded step's fit starts this long before the pose first left its rest: the command came earlier by
# the arm's delay and the start of its rise, unknown to the tool; the fit's delay takes the difference.
LEAD_S = 0.06


def find_steps(t: np.ndarray, p: np.ndarray, size: float) -> list[tuple[int, float]]:
    """(axis, time) of each step in recorded positions p (N, 3): the axis whose position passes half the step
    from its mean over the REST_BEFORE_S before, and the time of the last sample before it left that rest
    by a tenth of the step (or four standard deviations of its noise). A later step is looked for only after
    RECORD_S."""
    steps, k = [], 0
    while k < len(t):
        rest = (t >= t[k] - REST_BEFORE_S) & (t < t[k])
        if rest.sum() >= 5:
            moved = np.abs(p[k] - p[rest].mean(axis=0))
            axis = int(np.argmax(moved))
            if moved[axis] >= STEP_SHARE * size:
                # back to the first sample that left the rest by a tenth of the step (or 4 sigma of its noise)
                level, spread = p[rest, axis].mean(), max(0.1 * size, 4.0 * p[rest, axis].std())
                start = k
                while start > 0 and abs(p[start - 1, axis] - level) > spread:
                    start -= 1
                steps.append((axis, float(t[max(start - 1, 0)])))
                k = int(np.searchsorted(t, t[k] + RECORD_S))
                continue
        k += 1
    return steps


def fit_recorded(t: np.ndarray, p: np.ndarray, size: float, noise_std: float | None = None) -> dict[str, list]:
    """Per axis, the fits of the steps found in the recorded positions."""
    fits: dict[str, list] = {a: [] for a in AXES}
    for axis, moved in find_steps(t, p, size):
        start = moved - LEAD_S
        rest = (t >= start - REST_BEFORE_S) & (t < start)
        window = (t >= start) & (t < start + RECORD_S)
        y = p[window, axis] - p[rest, axis].mean()
        step = size * np.sign(y[-10:].mean())
        fits[AXES[axis]].append({"t": (t[window] - start).tolist(), "y": y.tolist(), "step": step,
                                 "fit": fit_step(t[window] - start, y, step, noise_std)})
    return fits


def steps_on_sim(size: float, repeats: int, rate_hz: float, out: Path, gauge_file: str = "") -> dict[str, list]:
    """Steps of the robot program on the simulated cell, each axis `repeats` times up and back down; the
    fits of the estimated poses (the truth is what the tests compare with, not what the fit sees)."""
    from .experiment import Experiment
    from .graph import Graph

    graph = Graph(out / "logs", client_name="profile_pose_identify")
    fits: dict[str, list] = {a: [] for a in AXES}
    try:
        exp = Experiment(graph, rate_hz, 5e-6, gauge_file=gauge_file)
        exp.start()
        exp.bridge(arm=False)
        for axis_index, axis in enumerate(AXES):
            direction = np.eye(3)[axis_index]
            for k in range(repeats):
                result = exp.step(False, direction, size)
                record = result["estimate"]
                if result["spoiled"] or not record["t"]:
                    print(f"  {axis} #{k + 1}: left out ({'; '.join(result['spoiled'])})", flush=True)
                    continue
                t, y = np.array(record["t"]), np.array(record["y"])
                fit = fit_step(t, y, size)
                fits[axis].append({"t": record["t"], "y": record["y"], "step": size, "fit": fit})
                print(f"  {axis} #{k + 1}: {describe(fit)}", flush=True)
    finally:
        graph.close()
    return fits


def describe(fit: ModeFit) -> str:
    return (f"f {fit.frequency_hz:.3f} +- {fit.frequency_sigma:.3f} Hz, zeta {fit.damping:.4f} +- "
            f"{fit.damping_sigma:.4f}, gain {fit.gain:.3f} +- {fit.gain_sigma:.3f}, delay "
            f"{1e3 * fit.delay_s:.1f} +- {1e3 * fit.delay_sigma:.1f} ms, residual {1e6 * fit.residual_rms:.1f} um")


def parameter_file(modes: dict[str, ModeFit], frequency: list[float], damping: list[float]) -> dict:
    """pd_compensator's modal_frequency and modal_damping: the identified translations, the given rotations
    (the gauge-based steps excite translations only)."""
    f, z = list(frequency), list(damping)
    for i, axis in enumerate(AXES):
        if axis in modes:
            f[i], z[i] = round(modes[axis].frequency_hz, 3), round(modes[axis].damping, 4)
    return {"pd_compensator": {"ros__parameters": {"modal_frequency": f, "modal_damping": z}}}


def plot(fits: dict[str, list], path: Path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(AXES), 1, figsize=(8, 8), sharex=True)
    for ax, axis in zip(axes, AXES):
        for item in fits[axis]:
            t, fit = np.array(item["t"]), item["fit"]
            ax.plot(t, 1e3 * np.array(item["y"]), ".", ms=2, alpha=0.5)
            model = fit.gain * item["step"] * step_response(t, fit.frequency_hz, fit.damping, fit.delay_s)
            ax.plot(t, 1e3 * model, "-", lw=1)
        ax.set_ylabel(f"{axis} (mm)")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time from the step (s)")
    fig.suptitle("open-loop steps (dots: estimated poses) and the fitted mode (lines)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def read_positions(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    from rosbags.highlevel import AnyReader

    t, p = [], []
    with AnyReader([bag]) as reader:
        for connection, _, data in reader.messages([c for c in reader.connections if c.topic == topic]):
            msg = reader.deserialize(data, connection.msgtype)
            pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
            t.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
            p.append([pose.position.x, pose.position.y, pose.position.z])
    if not t:
        raise SystemExit(f"error: no {topic} messages in {bag}")
    order = np.argsort(t)
    return np.array(t)[order], np.array(p)[order]


def main(argv=None) -> int:
    from ..nodes.parameters import defaults
    from ..nodes.pd_compensator import PARAMETERS

    compensator = defaults(PARAMETERS)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, help="a recording of a real cell's poses during small program steps")
    parser.add_argument("--topic", default="/pose", help="the poses in the bag (PoseStamped or with covariance)")
    parser.add_argument("--size", type=float, default=0.3, help="step size (mm): small keeps a nonlinear "
                        "damping near its small-motion value")
    parser.add_argument("--repeats", type=int, default=3, help="steps per axis (simulated cell)")
    parser.add_argument("--rate", type=float, default=83.333, help="control rate of the simulated cell (Hz)")
    parser.add_argument("--gauge", default="", help="gauge YAML of the simulated cell")
    parser.add_argument("--params-out", type=Path, help="also write the parameter file here (e.g. for "
                        "profile_pose experiment --compensator-params)")
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "identify")
    size = args.size * 1e-3
    if args.bag:
        fits = fit_recorded(*read_positions(args.bag, args.topic), size)
    else:
        print(f"open-loop steps of {args.size:g} mm on the simulated cell at {args.rate:g} Hz, {args.repeats} per "
              f"axis; logs in {out / 'logs'}", flush=True)
        fits = steps_on_sim(size, args.repeats, args.rate, out, args.gauge)
    modes = {axis: combine([item["fit"] for item in items]) for axis, items in fits.items() if items}
    if not modes:
        print("error: no step could be fitted", file=sys.stderr)
        return 1
    print(table(["axis", "steps", "frequency (Hz)", "damping", "gain", "delay (ms)", "residual (um)"],
                [[axis, str(len(fits[axis])), f"{m.frequency_hz:.3f} +- {m.frequency_sigma:.3f}",
                  f"{m.damping:.4f} +- {m.damping_sigma:.4f}", f"{m.gain:.3f} +- {m.gain_sigma:.3f}",
                  f"{1e3 * m.delay_s:.1f} +- {1e3 * m.delay_sigma:.1f}", f"{1e6 * m.residual_rms:.1f}"]
                 for axis, m in modes.items()], title=f"the arm's mode from {sum(map(len, fits.values()))} steps of "
                                                      f"{args.size:g} mm (uncertainties: 1 sigma)"))
    params = parameter_file(modes, compensator["modal_frequency"], compensator["modal_damping"])
    text = ("# profile_pose identify: pd_compensator's modal model, identified from "
            + (f"{args.bag}" if args.bag else "the simulated cell") + "\n"
            + yaml.safe_dump(params, default_flow_style=None, sort_keys=False))
    for path in [out / "modal.yaml"] + ([args.params_out] if args.params_out else []):
        path.write_text(text)
    write_json(out / "identify.json", {"size_mm": args.size, "modes": {a: m.as_dict() for a, m in modes.items()},
                                       "fits": {a: [i["fit"].as_dict() for i in items] for a, items in fits.items()},
                                       "parameters": params})
    figure = plot(fits, out / "identify.png")
    print(f"parameters: {out / 'modal.yaml'} (pass it after cell.yaml); report: {out / 'identify.json'}; "
          f"plot: {figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
