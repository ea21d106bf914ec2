#!/usr/bin/env bash
# Create or update the project environment: .venv (Python 3.11) with ROS 2 Jazzy from
# wheels, the library's dependencies, the test tools, and magcal_ros installed editable
# (so `magcal` and the node executables are in .venv/bin).
#
#   scripts/setup_env.sh         # what `make setup` runs; safe to run again
#
# Environment: PYTHON (a Python 3.11 interpreter; default: the first of python3.11, python3,
# python on PATH that is 3.11), VENV (default .venv in the repository).
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "${repo}"
VENV="${VENV:-${repo}/.venv}"
STAMP="${VENV}/.magcal_setup_stamp"
EXECUTABLES=(magcal fluxgate_driver fluxgate_sim calibration_node corrector_node)

is_py311() {
    command -v "$1" >/dev/null 2>&1 \
        && "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null
}
if [ -z "${PYTHON:-}" ]; then
    for candidate in python3.11 python3 python; do
        if is_py311 "${candidate}"; then PYTHON="${candidate}"; break; fi
    done
fi
if [ -z "${PYTHON:-}" ] || ! is_py311 "${PYTHON}"; then
    echo "setup: no Python 3.11 found (the ROS 2 Jazzy wheels need 3.11); install it or set" \
         "PYTHON=/path/to/python3.11" >&2
    exit 1
fi

# (Re)create the venv when it is missing or not Python 3.11 (the ROS Jazzy wheels need 3.11).
if [ -x "${VENV}/bin/python" ] \
        && ! "${VENV}/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "setup: ${VENV} is not a Python 3.11 environment; recreating it" >&2
    rm -rf "${VENV}"
fi
if [ ! -x "${VENV}/bin/python" ]; then
    echo "setup: creating ${VENV} with ${PYTHON}"
    "${PYTHON}" -m venv "${VENV}"
fi
# colcon must not crawl the venv's share/*/package.xml when a workspace contains this repo.
touch "${VENV}/COLCON_IGNORE"

pip_install() {
    # pip warns once per package about this machine's local index folders that lack it;
    # that noise is dropped, everything else pip says on stderr is kept.
    "${VENV}/bin/python" -m pip --disable-pip-version-check install -q "$@" \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2 || true)
}
echo "setup: installing dependencies from requirements.txt"
pip_install -r requirements.txt
echo "setup: installing magcal_ros (editable)"
pip_install --no-deps -e .
echo "setup: building the message package magcal_interfaces (interfaces/)"
VENV="${VENV}" scripts/build_interfaces.sh

# Check the result: the ROS wheels import, and the console scripts exist in .venv/bin.
"${VENV}/bin/python" - <<'PY'
import importlib
for name in ('rclpy', 'rclpy.executors', 'sensor_msgs.msg', 'std_msgs.msg', 'std_srvs.srv',
             'diagnostic_msgs.msg', 'numpy', 'scipy', 'serial', 'yaml', 'matplotlib',
             'rosbags', 'ppigrf', 'zstandard', 'jsonschema', 'tqdm', 'pytest', 'hypothesis',
             'pytest_timeout', 'xdist', 'colcon_core', 'magcal_ros'):
    importlib.import_module(name)
PY
for exe in "${EXECUTABLES[@]}"; do
    if [ ! -x "${VENV}/bin/${exe}" ]; then
        echo "setup: ${VENV}/bin/${exe} is missing after the editable install" >&2
        exit 1
    fi
done
date -u +%Y-%m-%dT%H:%M:%SZ > "${STAMP}"
echo "setup: done (${VENV})"
