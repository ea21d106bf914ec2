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

from glob import glob

from setuptools import find_packages, setup

package_name = 'magcal_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config',
         sorted(glob('config/*.yaml') + glob('config/*.xml'))),
        ('share/' + package_name + '/launch', sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='magcal_ros maintainers',
    maintainer_email='magcal@example.com',
    description=(
        'Calibration, model diagnosis and live correction of a four-fluxgate cross '
        'magnetic gradient tensor array (ROS 2 nodes plus an offline tool).'
    ),
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'fluxgate_driver = magcal_ros.ros.driver_node:main',
            'calibration_node = magcal_ros.ros.calibration_node:main',
            'corrector_node = magcal_ros.ros.corrector_node:main',
            'fluxgate_sim = magcal_ros.ros.sim_node:main',
            'magcal = magcal_ros.cli:main',
        ],
    },
)
