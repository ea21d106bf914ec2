#!/usr/bin/env bash
# The magcal_ros main job on the simulated array (README "Demo"): starts fluxgate_sim,
# fluxgate_driver, calibration_node and corrector_node, calibrates while the simulated array
# tumbles (30 s, longer until its attitudes are covered), then prints the total-field and
# gradient-tensor errors before and after correction next to the noise floor and writes
# figures to ./demo_out (or --out DIR).
#
#   scripts/demo.sh [--out DIR] [--collect-s 30] [--record-s 15] [--model base] ...
#   scripts/demo.sh --loop [--seed N]   (a hidden effect found and removed through ROS)
#   scripts/demo.sh --learn   (the vehicle drives, an offset changes, the node learns it)
#   scripts/demo.sh --site-gradient [GXX,GXY,GXZ,GYY,GYZ]   (offline before/after, nT/m)
#   scripts/demo.sh --help
#
# Runs in the project's loopback-only ROS environment (scripts/ros_env.sh: loopback Fast DDS
# profile, private ROS_DOMAIN_ID, .venv/bin first on PATH). Exit status 0 only if everything
# worked and the corrected errors are at the noise floor.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
# shellcheck source=ros_env.sh
source "${repo}/scripts/ros_env.sh"
python="${repo}/.venv/bin/python"
if [ ! -x "${python}" ]; then
    echo "scripts/demo.sh: ${python} not found; run 'make setup' first (or 'make demo')" >&2
    exit 2
fi
# --site-gradient[=G]: the offline before/after of a site gradient (scripts/demo_site_gradient.py)
for arg in "$@"; do
    case "${arg}" in
        --site-gradient|--site-gradient=*)
            exec "${python}" "${repo}/scripts/demo_site_gradient.py" "$@" ;;
        --loop)
            exec "${python}" "${repo}/scripts/demo_loop.py" "$@" ;;
        --learn)
            exec "${python}" "${repo}/scripts/demo_learn.py" "$@" ;;
    esac
done
exec "${python}" "${repo}/scripts/demo.py" "$@"
