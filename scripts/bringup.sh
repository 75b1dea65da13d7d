#!/usr/bin/env bash
# Bring a cell up without launch files: the simulated cell and the four nodes (or, with --hardware, the
# four nodes against the real devices), each its own process; Ctrl-C stops them, bridge first.
#   scripts/bringup.sh                      # simulated cell, config/cell.yaml
#   scripts/bringup.sh --record             # ... and record its topics under runs/<timestamp>/bag
#   scripts/bringup.sh --namespace cell2    # a second cell beside the first
#   scripts/bringup.sh --composed           # the four nodes in one cell_container process
#   scripts/bringup.sh --hardware --params-file my_cell.yaml
source "$(dirname "$0")/venv.sh"
exec "$VENV/bin/profile_pose_bringup" "$@"
