#!/usr/bin/env bash
# Build the message package interfaces/magcal_interfaces (GradientTensorStamped) with the
# ROS 2 Jazzy wheels of the project environment and install it into that environment, so
# that `import magcal_interfaces.msg` works in .venv (`make setup` runs this).
#
#   scripts/build_interfaces.sh          # VENV (default .venv), BUILD_DIR (default build/)
#
# On a real ROS 2 install build it with colcon instead (README, "Live: ROS 2").
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
VENV="${VENV:-${repo}/.venv}"
BUILD_DIR="${BUILD_DIR:-${repo}/build}/magcal_interfaces"
py="${VENV}/bin/python"
for tool in cmake cc c++; do
    if ! command -v "${tool}" >/dev/null 2>&1; then
        echo "build_interfaces: ${tool} not found; install cmake and a C/C++ compiler" \
             "(Debian: apt-get install cmake g++) to build magcal_interfaces" >&2
        exit 1
    fi
done
py_include="$("${py}" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
np_include="$("${py}" -c 'import numpy; print(numpy.get_include())')"
if [ ! -f "${py_include}/Python.h" ]; then
    echo "build_interfaces: no Python.h in ${py_include}; install the Python 3.11 headers" >&2
    exit 1
fi
rm -rf "${BUILD_DIR}"
mkdir -p "${BUILD_DIR}"
log="${BUILD_DIR}/build.log"
# ament_index_get_resources finds the type supports through AMENT_PREFIX_PATH
if ! AMENT_PREFIX_PATH="${VENV}" cmake -S "${repo}/interfaces/magcal_interfaces" \
        -B "${BUILD_DIR}" -DCMAKE_PREFIX_PATH="${VENV}" -DCMAKE_INSTALL_PREFIX="${VENV}" \
        -DPython3_EXECUTABLE="${py}" -DBUILD_TESTING=OFF \
        -DCMAKE_PROJECT_INCLUDE="${repo}/interfaces/ros_wheels_fix.cmake" \
        -DMAGCAL_PYTHON_INCLUDE="${py_include}" -DMAGCAL_NUMPY_INCLUDE="${np_include}" \
        >"${log}" 2>&1 \
   || ! AMENT_PREFIX_PATH="${VENV}" cmake --build "${BUILD_DIR}" -j 2 >>"${log}" 2>&1 \
   || ! cmake --install "${BUILD_DIR}" >>"${log}" 2>&1; then
    tail -n 30 "${log}" >&2
    echo "build_interfaces: building magcal_interfaces failed (full log: ${log})" >&2
    exit 1
fi
"${py}" -c 'from magcal_interfaces.msg import GradientTensorStamped; GradientTensorStamped()'
echo "build_interfaces: magcal_interfaces installed into ${VENV}"
