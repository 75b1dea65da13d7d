#!/usr/bin/env bash
# The main job: the simulated estimation demo (see README). Extra arguments go to the demo.
source "$(dirname "$0")/venv.sh"
exec "$VENV/bin/profile_pose_demo" "$@"
