# Copyright 2026 The magcal_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

# Build fix for the ROS 2 Jazzy *wheels* only (scripts/build_interfaces.sh passes this file as
# CMAKE_PROJECT_INCLUDE); a real ROS install does not need it.
#
# The wheels' exported CMake targets (e.g. std_msgs::std_msgs__rosidl_generator_py) name the
# Python include directory of the machine that built the wheels (/opt/python/cp311-cp311/...),
# and its numpy), which do not exist here, so CMake refuses to generate. At the end of the
# configure step this replaces them with MAGCAL_PYTHON_INCLUDE and MAGCAL_NUMPY_INCLUDE (this
# interpreter's include folder and numpy.get_include()).
function(_magcal_fix_wheel_python_include)
  get_directory_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" IMPORTED_TARGETS)
  foreach(_t IN LISTS _targets)
    get_target_property(_dirs ${_t} INTERFACE_INCLUDE_DIRECTORIES)
    if(_dirs AND "${_dirs}" MATCHES "/opt/python/cp[0-9]+-cp[0-9]+/include")
      list(TRANSFORM _dirs REPLACE "^/opt/python/cp[0-9]+-cp[0-9]+/include/python[0-9.]+$"
        "${MAGCAL_PYTHON_INCLUDE}")
      list(TRANSFORM _dirs REPLACE "^/opt/python/cp[0-9]+-cp[0-9]+/.*/numpy/.*include$"
        "${MAGCAL_NUMPY_INCLUDE}")
      set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_dirs}")
    endif()
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _magcal_fix_wheel_python_include)
