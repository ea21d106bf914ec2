#!/usr/bin/env bash
# Loopback-only ROS 2 environment for magcal_ros's own runs (tests, demo, benchmarks).
#
#   source scripts/ros_env.sh          # in an interactive shell (bash or zsh)
#   scripts/ros_env.sh CMD [ARGS...]   # run one command in that environment
#
# Sets, for Fast DDS (rmw_fastrtps_cpp, the Jazzy default):
#   FASTRTPS_DEFAULT_PROFILES_FILE, FASTDDS_DEFAULT_PROFILES_FILE
#       absolute path of config/fastdds_loopback.xml (shared memory + UDPv4 on 127.0.0.1 only,
#       no multicast, unicast discovery with initial peer 127.0.0.1)
#   ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT   so the profile is used unchanged
#   RMW_IMPLEMENTATION=rmw_fastrtps_cpp
#   ROS_DOMAIN_ID   kept if already set, else 1 + (PID mod 101): 1..101, one per shell/run
# and unsets ROS_LOCALHOST_ONLY and ROS_STATIC_PEERS (they would override or extend the
# profile). If the project's .venv exists, its bin/ is put first on PATH so that `magcal`
# and the node executables are found.
# Users on a real robot keep their own DDS settings: do not source this there.

if [ -n "${BASH_VERSION:-}" ]; then
    _magcal_env_src="${BASH_SOURCE[0]}"
elif [ -n "${ZSH_VERSION:-}" ]; then
    eval '_magcal_env_src="${(%):-%x}"'
else
    echo "scripts/ros_env.sh: source it from bash or zsh" >&2
    return 2 2>/dev/null || exit 2
fi
_magcal_repo="$(cd "$(dirname "${_magcal_env_src}")/.." && pwd -P)"

export FASTRTPS_DEFAULT_PROFILES_FILE="${_magcal_repo}/config/fastdds_loopback.xml"
export FASTDDS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
unset ROS_LOCALHOST_ONLY ROS_STATIC_PEERS
if [ -z "${ROS_DOMAIN_ID:-}" ]; then
    export ROS_DOMAIN_ID=$(( 1 + $$ % 101 ))
fi
case ":${PATH}:" in
    *":${_magcal_repo}/.venv/bin:"*) ;;
    *) if [ -d "${_magcal_repo}/.venv/bin" ]; then
           export PATH="${_magcal_repo}/.venv/bin:${PATH}"
       fi ;;
esac
unset _magcal_env_src _magcal_repo

# Executed rather than sourced: run the given command in this environment.
if [ -n "${BASH_VERSION:-}" ] && [ "${BASH_SOURCE[0]}" = "$0" ]; then
    if [ "$#" -eq 0 ]; then
        echo "usage: source scripts/ros_env.sh | scripts/ros_env.sh CMD [ARGS...]" >&2
        exit 2
    fi
    exec "$@"
fi
