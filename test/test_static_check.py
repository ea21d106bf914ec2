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

"""magcal_ros.core.data.static_check: static recordings against a calibration, hand-made fields."""
from magcal_ros.core.data.static_check import check_static
import numpy as np
import pytest

F = 50000.0


def static(direction, magnitude, n=2000, noise=100.0, seed=0):
    """(n, 3) corrected readings of a sensor lying still: a field plus white noise, nT."""
    d = np.asarray(direction, float)
    return (magnitude * d / np.linalg.norm(d)
            + np.random.default_rng(seed).normal(size=(n, 3)) * noise)


def test_one_field_everywhere_is_consistent():
    res = check_static({'a': static((1, 0, -1), F), 'b': static((0, 1, 1), F + 50, seed=1),
                        'c': static((-1, 0, 0.5), F - 40, seed=2)}, F, residual_rms_nt=100.0)
    assert res.consistent and res.tolerance_nt == 300.0
    assert res.findings[0].startswith('all 3 recordings give |B| within 300 nT')
    assert [r['b_nt'] for r in res.rows] == pytest.approx([F, F + 50, F - 40], abs=10.0)


def test_same_attitude_different_field_is_named():
    res = check_static({'a': static((1, 0, -1), F), 'b': static((1, 0.02, -1), F - 7000,
                                                                seed=1)},
                       F, residual_rms_nt=250.0)
    assert not res.consistent
    (a, b, ang, diff), = res.same_attitude
    assert (a, b) == ('a', 'b') and ang < 2.0 and diff == pytest.approx(-7000, abs=20)
    assert 'same attitude' in res.findings[0] and 'changed between these recordings' in \
        res.findings[0]


def test_other_attitudes_agreeing_off_the_reference_mean_another_field():
    res = check_static({'a': static((1, 0, 0), F - 2000), 'b': static((0, 0, 1), F - 2040,
                                                                      seed=1)},
                       F, residual_rms_nt=250.0)
    assert not res.consistent and len(res.findings) == 1
    assert 'the calibration holds there' in res.findings[0]
    assert 'field differs from the calibration' in res.findings[0]


def test_no_recordings():
    with pytest.raises(ValueError, match='no static recordings'):
        check_static({}, F, 1.0)


def test_other_disagreements_are_put_down_to_a_known_change():
    res = check_static({'a': static((1, 0, -1), F), 'b': static((1, 0.02, -1), F - 7000,
                                                                seed=1),
                        'c': static((0, 1, 0), F, seed=2)}, F, residual_rms_nt=250.0)
    assert sum('as expected after the change of field' in t for t in res.findings) == 1
    assert not any('cannot tell which' in t for t in res.findings)
