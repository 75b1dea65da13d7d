#!/usr/bin/env bash
# The main job: the simulated cell with all nodes, each its own process, and the paper's closed-loop
# step experiment (Table IV): open vs closed loop, 1 and 2 mm steps on x, y, z and x+y+z, on the designed
# gauge with the dense refinement (every point fitted to its face: the lowest noise on the weakly determined
# y axis; it keeps up at 83.3 Hz on 2 cores; --gauge and --refine-model override). Prints the
# table and writes the plots and JSON under runs/. Extra arguments go to profile_pose experiment.
#
# --fast: the fast, damped steps instead (docs/robot_side.md): the arm's mode identified first on the cell
# (profile_pose identify), the profiler at 1 kHz with each controller period's poses fused, planned steps
# (config/fast_steps.yaml; with --rate 250 also config/fast_steps_250hz.yaml). Not recorded: a bag of 1 kHz
# profiles would be ~0.5 GB.
source "$(dirname "$0")/venv.sh"
GAUGE="$ROOT/config/gauge_designed_n6.yaml"
if [ "${1:-}" = "--fast" ]; then
  shift
  MODEL="$ROOT/runs/identified_modal.yaml"
  LAYERS=("$ROOT/config/fast_steps.yaml")
  previous=""
  for argument in "$@"; do
    if [ "$argument" = "--rate=250" ] || { [ "$previous" = "--rate" ] && [ "$argument" = "250" ]; }; then
      LAYERS+=("$ROOT/config/fast_steps_250hz.yaml")
    fi
    previous="$argument"
  done
  "$VENV/bin/profile_pose" identify --gauge "$GAUGE" --size 1.5 --params-out "$MODEL" --out "$ROOT/runs"
  exec "$VENV/bin/profile_pose" experiment --repeats 2 --gauge "$GAUGE" --no-bag --profile-rate 1000 \
    --estimator-in-driver --compensator-in-bridge \
    --compensator-params "${LAYERS[@]}" "$MODEL" "$@"
fi
exec "$VENV/bin/profile_pose" experiment --repeats 2 --gauge "$GAUGE" "$@"
