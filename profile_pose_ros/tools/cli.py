"""profile_pose: the package's research, benchmark and commissioning tools behind one command.

    profile_pose experiment --repeats 2      the paper's Table IV step experiment on the simulated cell
    profile_pose <tool> --help               each tool's own options

The runtime executables (the nodes, sim_cell, bag_recorder, bag_player, profile_pose_bag and
profile_pose_bringup) stay executables of their own, as `ros2 run` expects.
"""
from __future__ import annotations

import importlib
import sys

# subcommand -> (module under profile_pose_ros.tools, what it is for)
TOOLS = {
    "experiment": ("experiment", "the closed-loop step experiment (paper IV-C, Table IV) on the simulated cell"),
    "calibration-study": ("calibration_study", "profile_pose_calibrate on sim_cells with hidden placements, "
                          "against the truth"),
    "identify": ("identify", "the arm's mode per axis, for the modal compensator (sim or a bag)"),
    "gauge": ("gauge_cli", "check, design and export gauges (paper III-D)"),
    "profiler-check": ("profiler_check", "sim_cell + profiler_driver + pose_estimator as processes, checked"),
    "replay": ("replay", "re-run the estimator on a bag's profiles, offline"),
    "latency": ("latency", "the loop's latency budget, stage by stage"),
    "benchmark": ("benchmark", "the paper's Table III, side by side on this machine"),
    "node-benchmark": ("node_benchmark", "the pose_estimator node under load, over DDS between processes"),
    "study": ("study", "the paper's simulation study (III-B, III-C) with Cramer-Rao bounds"),
    "robustness": ("robustness", "the estimator on spiky, gapped and noisy profiles: refusals, wrong poses, NEES"),
    "demo": ("estimation_demo", "a quick estimation demo on rendered profiles"),
    "soak": ("soak", "the closed loop for a long time, every profile and correction accounted for"),
    "faults": ("faults", "a factory's faults injected into the running closed loop"),
    "fuzz": ("fuzz", "every decoder and parser of outside input against mutated input"),
}


def usage() -> str:
    width = max(map(len, TOOLS))
    rows = "\n".join(f"  {name:<{width}}  {about}" for name, (_, about) in TOOLS.items())
    return f"usage: profile_pose <tool> [options]\n\ntools:\n{rows}\n\n`profile_pose <tool> --help` for its options."


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in TOOLS:
        print(f"profile_pose: no tool {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"profile_pose_ros.tools.{TOOLS[name][0]}")
    sys.argv[0] = f"profile_pose {name}"  # argparse's prog, in each tool's usage and errors
    return module.main(rest)


if __name__ == "__main__":
    sys.exit(main())
