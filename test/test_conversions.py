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

"""Tests of magcal_ros.units and magcal_ros.ros.conversions (nT <-> T message conversions)."""

from builtin_interfaces.msg import Time as TimeMsg
from hypothesis import given, settings
from hypothesis import strategies as st
from magcal_ros.ros import conversions as conv
from magcal_ros.units import NT_PER_T, nt_to_t, t_to_nt
import numpy as np
import pytest
import rclpy.time
from sensor_msgs.msg import MagneticField, Temperature
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

# Earth-field-sized values, nT (and gradients in nT/m of the same order).
finite_nt = st.floats(min_value=-2e5, max_value=2e5, allow_nan=False, allow_infinity=False)
# Converting nT -> T -> nT is one division and one multiplication by 1e9, each rounded to
# float64: the round trip is exact to within a few ulp, i.e. relative 1e-15.
RTOL = 1e-15


def test_units_constant_and_helpers():
    assert NT_PER_T == 1e9
    assert nt_to_t(50000.0) == pytest.approx(5e-5, rel=RTOL)
    assert t_to_nt(5e-5) == pytest.approx(50000.0, rel=RTOL)
    arr = nt_to_t([[1.0, -2.0], [3.0, 4.0]])
    assert arr.shape == (2, 2) and arr.dtype == np.float64
    np.testing.assert_allclose(arr, [[1e-9, -2e-9], [3e-9, 4e-9]], rtol=RTOL)


def test_field_msg_is_tesla_with_header():
    field_nt = [12345.6, -2345.1, 43210.9]
    stamp = TimeMsg(sec=1700000000, nanosec=123456789)
    msg = conv.field_nt_to_msg(field_nt, stamp=stamp, frame_id='fluxgate2')
    assert isinstance(msg, MagneticField)
    assert msg.header.frame_id == 'fluxgate2'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1700000000, 123456789)
    assert msg.header.stamp is not stamp
    np.testing.assert_allclose(
        [msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z],
        [12345.6e-9, -2345.1e-9, 43210.9e-9], rtol=RTOL)
    # no covariance given -> all zeros ("unknown" per the message definition)
    assert not np.any(msg.magnetic_field_covariance)


def test_scalar_variance_becomes_diagonal_tesla_squared():
    msg = conv.field_nt_to_msg([1.0, 2.0, 3.0], covariance_nt2=9.0)    # sigma 3 nT
    cov_t2 = np.asarray(msg.magnetic_field_covariance).reshape(3, 3)
    np.testing.assert_allclose(cov_t2, np.eye(3) * 9e-18, rtol=RTOL, atol=0.0)
    np.testing.assert_allclose(conv.msg_to_covariance_nt2(msg), np.eye(3) * 9.0, rtol=RTOL)


def test_full_covariance_is_row_major():
    cov = np.array([[4.0, 1.0, -0.5], [1.0, 9.0, 0.25], [-0.5, 0.25, 16.0]])
    msg = conv.field_nt_to_msg([0.0, 0.0, 0.0], covariance_nt2=cov)
    flat = list(msg.magnetic_field_covariance)
    # row-major: element (0, 1) at index 1, (1, 0) at index 3, (2, 1) at index 7
    assert flat[1] == pytest.approx(1e-18, rel=RTOL)
    assert flat[2] == pytest.approx(-0.5e-18, rel=RTOL)
    assert flat[7] == pytest.approx(0.25e-18, rel=RTOL)
    np.testing.assert_allclose(conv.msg_to_covariance_nt2(msg), cov, rtol=RTOL)


@settings(max_examples=200, deadline=None)
@given(st.tuples(finite_nt, finite_nt, finite_nt))
def test_field_round_trip(field_nt):
    back = conv.msg_to_field_nt(conv.field_nt_to_msg(field_nt))
    assert back.shape == (3,)
    np.testing.assert_allclose(back, field_nt, rtol=RTOL, atol=1e-20)


@settings(max_examples=200, deadline=None)
@given(st.lists(finite_nt, min_size=9, max_size=9))
def test_tensor_round_trip(values):
    g = np.array(values).reshape(3, 3)
    back = conv.msg_to_tensor(conv.tensor_to_msg(g))
    assert back.shape == (3, 3)
    np.testing.assert_allclose(back, g, rtol=RTOL, atol=1e-20)


def test_tensor_layout_and_units():
    g = np.arange(9.0).reshape(3, 3) * 10.0 - 40.0      # nT/m, distinct entries
    msg = conv.tensor_to_msg(g)
    assert isinstance(msg, Float64MultiArray)
    dims = [(d.label, d.size, d.stride) for d in msg.layout.dim]
    assert dims == [('row', 3, 9), ('col', 3, 3)]
    assert msg.layout.data_offset == 0
    # row-major in T/m: element (1, 2) is data[1 * 3 + 2]
    assert msg.data[5] == pytest.approx(g[1, 2] * 1e-9, rel=RTOL)
    np.testing.assert_allclose(msg.data, g.ravel() * 1e-9, rtol=RTOL)


def test_msg_to_tensor_honours_data_offset():
    msg = conv.tensor_to_msg(np.eye(3) * 7.0)
    msg.layout.data_offset = 2
    msg.data = [99.0, 99.0] + list(msg.data)
    np.testing.assert_allclose(conv.msg_to_tensor(msg), np.eye(3) * 7.0, rtol=RTOL)


def test_msg_to_tensor_rejects_other_layouts():
    msg = conv.tensor_to_msg(np.zeros((3, 3)))
    msg.layout.dim = [MultiArrayDimension(label='col', size=3, stride=9),
                      MultiArrayDimension(label='row', size=3, stride=3)]
    with pytest.raises(ValueError, match='layout must be'):
        conv.msg_to_tensor(msg)
    msg = Float64MultiArray(data=[0.0] * 9)       # no layout at all
    with pytest.raises(ValueError, match='layout must be'):
        conv.msg_to_tensor(msg)
    msg = conv.tensor_to_msg(np.zeros((3, 3)))
    msg.data = [0.0] * 8
    with pytest.raises(ValueError, match='needs 9 values'):
        conv.msg_to_tensor(msg)


def test_temperature_msg():
    msg = conv.temperature_msg(24.31, stamp=12.5, frame_id='fluxgate1', variance_c2=0.01)
    assert isinstance(msg, Temperature)
    assert msg.temperature == pytest.approx(24.31)
    assert msg.variance == pytest.approx(0.01)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 500000000)
    assert msg.header.frame_id == 'fluxgate1'


def test_stamp_forms():
    t = rclpy.time.Time(seconds=3, nanoseconds=250)
    s = conv.to_stamp(t)
    assert (s.sec, s.nanosec) == (3, 250)
    assert conv.stamp_to_seconds(s) == pytest.approx(3.00000025, abs=1e-12)
    s = conv.to_stamp(1.999999999)
    assert (s.sec, s.nanosec) == (1, 999999999)
    s = conv.to_stamp(None)
    assert (s.sec, s.nanosec) == (0, 0)
    # float seconds survive stamp -> seconds to well below a microsecond
    assert conv.stamp_to_seconds(conv.to_stamp(1700000000.123456)) == \
        pytest.approx(1700000000.123456, abs=1e-6)


@pytest.mark.parametrize('bad, match', [
    ([1.0, 2.0], r'shape \(3,\)'),
    ([[1.0, 2.0, 3.0]], r'shape \(3,\)'),
    ([1.0, float('nan'), 3.0], 'must be finite'),
    ([1.0, 2.0, float('inf')], 'must be finite'),
])
def test_field_rejects_bad_vectors(bad, match):
    with pytest.raises(ValueError, match=match):
        conv.field_nt_to_msg(bad)


@pytest.mark.parametrize('cov, match', [
    (-1.0, 'finite and >= 0'),
    (float('nan'), 'finite and >= 0'),
    (np.eye(2), r'\(3, 3\) matrix'),
    (np.ones(3), r'\(3, 3\) matrix'),
    (np.diag([1.0, -1.0, 1.0]), 'diagonal must be >= 0'),
    (np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), 'symmetric'),
    (np.diag([1.0, np.inf, 1.0]), 'must be finite'),
])
def test_field_rejects_bad_covariance(cov, match):
    with pytest.raises(ValueError, match=match):
        conv.field_nt_to_msg([1.0, 2.0, 3.0], covariance_nt2=cov)


def test_other_bad_inputs():
    with pytest.raises(ValueError, match=r'shape \(3, 3\)'):
        conv.tensor_to_msg(np.zeros(9))
    with pytest.raises(ValueError, match='must be finite'):
        conv.tensor_to_msg(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match='non-negative number of seconds'):
        conv.to_stamp(-1.0)
    with pytest.raises(ValueError, match='builtin_interfaces/Time'):
        conv.to_stamp('now')
    with pytest.raises(ValueError, match='frame_id must be a str'):
        conv.field_nt_to_msg([0.0, 0.0, 0.0], frame_id=3)
    with pytest.raises(ValueError, match='temp_c must be finite'):
        conv.temperature_msg(float('nan'))
    with pytest.raises(ValueError, match='variance_c2'):
        conv.temperature_msg(20.0, variance_c2=-0.1)


def test_precomputed_covariance_gives_the_same_message():
    cov = np.array([[9.0, 1.0, 0.5], [1.0, 8.0, 0.2], [0.5, 0.2, 7.0]])
    a = conv.field_nt_to_msg([1.0, 2.0, 3.0], covariance_nt2=cov)
    b = conv.field_nt_to_msg([1.0, 2.0, 3.0],
                             covariance_t2=conv.covariance_to_t2(cov))
    assert list(a.magnetic_field_covariance) == list(b.magnetic_field_covariance)
    assert np.isclose(b.magnetic_field_covariance[0], 9e-18)
    with pytest.raises(ValueError, match='symmetric'):
        conv.covariance_to_t2(np.triu(cov))


@given(st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))
@settings(max_examples=50, deadline=None)
def test_field_set_in_place_equals_a_new_message(field_nt):
    # the corrector's hot path reuses the incoming message: the same bytes as a new one
    cov = conv.covariance_to_t2(9.0)
    incoming = conv.field_nt_to_msg([1.0, 2.0, 3.0], stamp=12.5, frame_id='fluxgate2',
                                    covariance_nt2=1.0)
    conv.set_field_nt(incoming, np.array(field_nt), cov)
    fresh = conv.field_nt_to_msg(field_nt, stamp=12.5, frame_id='fluxgate2', covariance_t2=cov)
    assert incoming == fresh


def test_unchecked_tensor_message_is_the_same():
    g = np.arange(9.0).reshape(3, 3) - 4.0
    assert conv.tensor_to_msg(g, check=False) == conv.tensor_to_msg(g)
    with pytest.raises(ValueError, match='finite'):
        conv.tensor_to_msg(g * np.nan)


def test_linear_correction_in_tesla_equals_the_one_in_nanotesla():
    """correct_msg_linear: A^-1 (raw - o) applied to tesla values, checked by hand in nT."""
    a_inv = np.array([[1.02, 0.01, -0.003], [0.0, 0.97, 0.02], [0.005, 0.0, 1.01]])
    offset_nt = np.array([120.0, -80.0, 30.0])
    raw_nt = np.array([21000.0, -4000.0, 43000.0])
    msg = conv.field_nt_to_msg(raw_nt, stamp=12.5, frame_id='fluxgate2')
    cov = conv.covariance_to_t2(np.eye(3) * 4.0)
    conv.correct_msg_linear(msg, conv.linear_to_t(a_inv, offset_nt), cov)
    d = raw_nt - offset_nt
    expected = [sum(a_inv[i, k] * d[k] for k in range(3)) for i in range(3)]
    np.testing.assert_allclose(conv.msg_to_field_nt(msg), expected, rtol=1e-12)
    np.testing.assert_allclose(msg.magnetic_field_covariance, np.eye(3).ravel() * 4e-18)
    assert msg.header.frame_id == 'fluxgate2' and msg.header.stamp.sec == 12


def test_residual_message_round_trip_hand_values():
    """
    Round-trip the calibration/residual message with hand values.

    calibration/residual: 2 nT scalar, 5 nT vector -> 2e-9 T, 5e-9 T in the documented
    places (data[j - 1], data[S + j - 1]) and back.
    """
    msg = conv.residual_to_msg(np.array([2.0, -1.0, 0.5]), np.array([5.0, 4.0, 3.0]))
    assert msg.data == pytest.approx([2e-9, -1e-9, 0.5e-9, 5e-9, 4e-9, 3e-9], abs=1e-15)
    scalar, vector = conv.msg_to_residual_nt(msg)
    np.testing.assert_allclose(scalar, [2.0, -1.0, 0.5])
    np.testing.assert_allclose(vector, [5.0, 4.0, 3.0])
    bad = Float64MultiArray(data=[0.0] * 6)            # no layout: refused, not guessed
    with pytest.raises(ValueError, match='layout'):
        conv.msg_to_residual_nt(bad)
    msg.data = msg.data[:5]
    with pytest.raises(ValueError, match='needs 6 values'):
        conv.msg_to_residual_nt(msg)
