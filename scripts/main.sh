#!/usr/bin/env bash
# The main job: the simulated cell with all nodes, each its own process, and the paper's closed-loop
# step experiment (Table IV): open vs closed loop, 1 and 2 mm steps on x, y, z and x+y+z, on the designed
# gauge with the dense refinement (every point fitted to its face: the lowest noise on the weakly determined
# y axis; it keeps up at 83.3 Hz on 2 cores; --gauge and --refine-model override). Prints the
# table and writes the plots and JSON under runs/. Extra arguments go to profile_pose experiment.
source "$(dirname "$0")/venv.sh"
exec "$VENV/bin/profile_pose" experiment --repeats 2 --gauge "$ROOT/config/gauge_designed_n6.yaml" "$@"
