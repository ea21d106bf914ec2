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

"""
The simulator's vehicle (issue 34 item 5): near level, part circles, an attitude in ENU.

Checked against hand-made references: the body z axis seen in the world (up in ENU), the
heading's sweep, the field in the body frame from the ENU attitude and the ENU field
(``R^T m``, the relation the attitude-aided fit uses), and truth terms of time (an offset step,
a window) added to the readings exactly where and when they are due.
"""
from magcal_ros.core.data.simulate import (attitude_enu, earth_field, ENU_TO_NED, simulate,
                                           vehicle_attitude)
import numpy as np
from scipy.spatial.transform import Rotation


def test_vehicle_is_level_within_its_tilt_and_turns_part_circles():
    t = np.arange(0.0, 300.0, 0.05)
    rot_ned = vehicle_attitude(t, period_s=60.0, tilt_deg=15.0, phases=(0.3, 1.0, 2.0))
    q_enu = attitude_enu(rot_ned.as_quat(scalar_first=True))
    r_enu = Rotation.from_quat(q_enu, scalar_first=True)
    up = r_enu.apply([0.0, 0.0, 1.0])
    # roll and pitch within 15 deg each: the body z axis within 21.2 deg of up
    tilt = np.degrees(np.arccos(up[:, 2]))
    assert tilt.max() < np.degrees(np.arccos(np.cos(np.radians(15)) ** 2)) + 0.01
    assert tilt.max() > 10.0                       # it does tilt
    fwd = r_enu.apply([1.0, 0.0, 0.0])
    heading = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    # back and forth: the heading turns both ways, by more than a circle overall
    rate = np.diff(heading)
    assert (rate > 0).mean() > 0.3 and (rate < 0).mean() > 0.3
    assert np.ptp(heading) > 2 * np.pi
    # the body field from the ENU attitude and the ENU field is the simulator's (NED) one
    b_ned = earth_field(50000.0, -7.0, 55.0)
    m_enu = ENU_TO_NED.T @ b_ned
    assert m_enu[2] < 0                             # the field points down: -up in ENU
    np.testing.assert_allclose(r_enu.inv().apply(m_enu), rot_ned.inv().apply(b_ned),
                               atol=1e-8)


def test_truth_terms_of_time_act_when_due():
    """An offset step at 60 s and a 5 s window: the readings differ by them, nothing else."""
    kw = {'n_samples': 1200, 'rate_hz': 10.0, 'trajectory': 'vehicle', 'attitude': True,
          'seed': 3}
    plain, _ = simulate(**kw)
    changed, _ = simulate(truth={'offset(step(60))@1': [100.0, -50.0, 0.0],
                                 'offset(window(30, 35))@2': [0.0, 400.0, 0.0]}, **kw)
    t = plain.t
    d1 = changed.raw[0] - plain.raw[0]
    d2 = changed.raw[1] - plain.raw[1]
    np.testing.assert_allclose(d1, (t >= 60)[:, None] * [100.0, -50.0, 0.0], atol=1e-9)
    inside = (t >= 30) & (t <= 35)
    np.testing.assert_allclose(d2, inside[:, None] * [0.0, 400.0, 0.0], atol=1e-9)
    np.testing.assert_array_equal(changed.raw[2:], plain.raw[2:])
    np.testing.assert_array_equal(changed.attitude, plain.attitude)


def test_fluxgate_sim_settings_of_the_vehicle(tmp_path):
    """--tilt-deg and imu_topic reach the simulator (the attitude is then simulated)."""
    from magcal_ros.sim import devices
    st = devices.resolve_settings(['--dir', str(tmp_path), '--trajectory', 'vehicle',
                                   '--tilt-deg', '25'])
    sim = devices.FluxgateSim(st)
    assert sim.sim.config.tilt_deg == 25.0 and not sim.sim.config.attitude
    st = devices.resolve_settings(['--dir', str(tmp_path), '--trajectory', 'vehicle'])
    st.imu_topic = 'imu'
    assert devices.FluxgateSim(st).sim.config.attitude
