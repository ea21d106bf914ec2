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
Fitted parameters no real sensor has, explained in words (real ones: paper 004, Table 1).

:func:`axis_maps` finds the signed permutation M (reading = M x the sensor's axes) of a
mirrored or turned sensor frame, recorded as ``axes(...)@j`` (:func:`mounting_notes`);
:func:`parameter_notes` names scales, angles and offsets beyond the limits below.
"""
from magcal_ros.core import effects as fx
from magcal_ros.core.model.notes import Note
import numpy as np

#: a scale factor further than this from 1 (and not a unit factor) is far from one
SCALE_FAR = 0.2
#: non-orthogonality or misalignment angles beyond this are named, degrees
ANGLE_WARN_DEG = 5.0
#: a scale within this many decades of 10^n (n != 0) is read as a unit factor
UNIT_DECADES = 0.15
#: what a scale of 10^n means: readings 10^n x the field in nT
UNIT_WORDS = {
    3: 'pT read as nT, or nT readings against a reference in uT',
    -3: 'uT read as nT, or uT readings against a reference in nT',
    5: 'readings 1e5 x the field: nT readings against a reference in gauss',
    -5: 'gauss read as nT (1 G = 1e5 nT)',
    -2: 'mG read as nT (1 mG = 100 nT)',
    2: 'nT readings against a reference in mG',
    -4: 'gauss read as uT',
    4: 'uT readings against a reference in gauss',
    -9: 'tesla read as nT',
    9: 'nT readings against a reference in tesla',
    1: 'a factor 10: mG read as uT, or a gain or range setting one decade off',
    -1: 'a factor 0.1: uT read as mG, or a gain or range setting one decade off',
}


def nearest_axis_map(a):
    """Signed permutation M (3, 3) maximising sum |a[i, k]| (linear_sum_assignment), a (3, 3)."""
    from scipy.optimize import linear_sum_assignment
    a = np.asarray(a, float)
    rows, cols = linear_sum_assignment(-np.abs(a))
    m = np.zeros((3, 3))
    m[rows, cols] = np.where(a[rows, cols] < 0, -1.0, 1.0)
    return m


def axis_maps(model, params):
    """{sensor j: M (3, 3)} of the sensors that need an axis map (sensor 1: sign changes only)."""
    out = {}
    for j in range(1, model.n_sensors + 1):
        old = model.axis_map(j)
        rest = old.T @ model.matrix(j, params)
        m = nearest_axis_map(rest)
        if j == 1 and not np.allclose(np.abs(m), np.eye(3)):
            m = np.diag(np.sign(np.diag(rest)) + (np.diag(rest) == 0))
        if not np.allclose(m, np.eye(3)):
            out[j] = old @ m
    return out


def with_axis_maps(model, maps):
    """Return a new Model: ``model``'s effects with ``axes(...)@j`` for each j of ``maps``."""
    from magcal_ros.core.model import Model
    spec = [t for t in model.spec()
            if not (t.startswith('axes(') and int(t.rsplit('@', 1)[1]) in maps)]
    spec += [f'axes({",".join(fx.axis_map_args(m))})@{j}' for j, m in sorted(maps.items())]
    return Model.from_spec(spec, model.n_sensors)


def _reading_text(m):
    """In words, what the readings of a sensor with axis map M (3, 3) carry."""
    ax = fx.AXIS_NAMES
    d = np.diag(m)
    if np.allclose(np.abs(m), np.eye(3)):
        neg = [ax[i] for i in range(3) if d[i] < 0]
        if len(neg) == 1:
            return (f'its {neg[0]} axis reads the field with reversed sign (that axis wired with '
                    'reversed polarity, or the sensor mounted mirrored)')
        if len(neg) == 3:
            return ('all three axes read the field with reversed sign (a mirrored sensor: an '
                    'inverted reference or a driver that negates the readings)')
        keep = [ax[i] for i in range(3) if d[i] > 0][0]
        return (f'it is turned by 180 deg about its {keep} axis relative to sensor 1 (mounted '
                f'upside down or back to front), or its {neg[0]} and {neg[1]} axes are both '
                'wired reversed')
    swapped = [ax[i] for i in range(3) if abs(m[i, i]) < 0.5]
    if len(swapped) == 2 and np.all(m[np.abs(m) > 0.5] > 0):
        return (f'its {swapped[0]} and {swapped[1]} readings are exchanged (the two channels '
                'or wires swapped, or the driver reading them in another order)')
    if np.linalg.det(m) > 0:
        return (f'it is mounted turned by 90 deg: its readings x, y, z carry its axes '
                f'({", ".join(fx.axis_map_args(m))})')
    return (f'its readings x, y, z carry its axes ({", ".join(fx.axis_map_args(m))}): axes '
            'exchanged and reversed in the wiring or the mounting')


def mounting_notes(maps, before, after, n_sensors):
    """
    Name each axis map found in a Note of kind ``mounting``.

    ``maps`` of :func:`axis_maps`; ``before``, ``after`` {j: (scales (3,), largest angle
    deg)} without and with them; ``n_sensors`` (a map shared by sensors 2..S is sensor 1's).
    """
    out = []
    shared = (n_sensors >= 3 and sorted(maps) == list(range(2, n_sensors + 1))
              and all(np.allclose(maps[j], maps[2]) for j in maps))
    for j, m in sorted(maps.items()):
        k0, ang0 = before[j]
        k1, ang1 = after[j]
        token = f'axes({",".join(fx.axis_map_args(m))})@{j}'
        mirror = (' (det A < 0: a mirrored, left-handed sensor frame, which no rotation of a '
                  'correct sensor gives)' if np.linalg.det(m) < 0 else '')
        text = (f'sensor {j}: {_reading_text(m)}{mirror}; without the map the fit gives scale '
                f'factors {", ".join(f"{k:+.3f}" for k in k0)} and angles up to {ang0:.0f} '
                f'deg; the calibration records it as {token} (reading = map x sensor axes, no '
                f'parameters) with scales {", ".join(f"{k:.3f}" for k in k1)} and angles up to '
                f'{ang1:.1f} deg after it, so the correction is right; fix the wiring or '
                'mounting, or keep the map')
        if shared and j == 2:
            text += ('; every sensor but sensor 1 shows this map: more likely sensor 1 is the '
                     'one wired or mounted so (it defines the array frame, so the maps are '
                     "recorded on the others and the array frame is sensor 1's own)")
        out.append(Note(text, 'mounting', j))
    return out


def linear_summary(model, params):
    """{sensor j: (scales (3,), nonorth angles (3,) rad, misalignment angle rad)} after maps."""
    out = {}
    for j in range(1, model.n_sensors + 1):
        parts = fx.decompose_linear(model.axis_map(j).T @ model.matrix(j, params), np.zeros(3))
        k = np.sign(np.diag(parts.u)) * parts.scale     # all negative when det A < 0
        cos = np.clip((np.trace(parts.q) - 1) / 2, -1.0, 1.0)
        out[j] = (k, np.array(parts.nonorth), float(np.arccos(cos)))
    return out


def fitted_scales_angles(model, params):
    """{sensor j: (scales (3,), largest |angle| deg)} as the parameters (else A_j) state them."""
    out = {}
    for j, (k, no, mis) in linear_summary(model, params).items():
        angles = [np.degrees(max(np.abs(no).max(), mis))]
        for eff, sl in zip(model.effects[j - 1], model.slices[j - 1]):
            if eff.name == 'scale':
                k = np.asarray(params[sl], float)
            elif eff.name in ('nonorthogonality', 'misalignment'):
                wrapped = (np.asarray(params[sl]) + np.pi) % (2 * np.pi) - np.pi
                angles.append(np.degrees(np.abs(wrapped).max()))
        out[j] = (k, float(max(angles)))
    return out


def _unit_decade(k):
    n = int(np.round(np.log10(k))) if k > 0 else 0
    return n if n != 0 and abs(np.log10(k) - n) < UNIT_DECADES else None


def parameter_notes(model, params, raw, field_nt):
    """Name values no real sensor has (Notes ``parameters``): raw (S, N, 3), field_nt nT."""
    from magcal_ros.core.model.calibration import Calibration
    cal = Calibration(model, params)
    lin = linear_summary(model, params)
    out = []

    def flag(j, text):
        out.append(Note(f'{text}; the calibration file records the value as fitted, with this '
                        'warning in its provenance', 'parameters', j))
    scales = np.array([lin[j][0] for j in sorted(lin)])
    common = float(np.median(scales))
    scales_checked = not (scales.size > 3 and abs(common - 1) > SCALE_FAR
                          and np.all(np.abs(scales / common - 1) < 0.1))
    if not scales_checked:
        n = _unit_decade(common)
        why = (f'{UNIT_WORDS[n]}' if n in UNIT_WORDS else
               f'the reference magnitude ({field_nt:.0f} nT) is off by that factor, or every '
               'sensor is converted with the wrong gain')
        flag(None, f'every sensor: scale factors near {common:.4g} (a real sensor has near 1): '
                   f'{why}')
    for j in sorted(lin):
        k, no, mis = lin[j]
        decades = {_unit_decade(kk) for kk in k}
        if scales_checked and len(decades) == 1 and None not in decades:
            n = decades.pop()
            words = UNIT_WORDS.get(n, 'another unit')
            flag(j, f'sensor {j}: scale factors {", ".join(f"{kk:.4g}" for kk in k)}: its '
                    f'readings are ~{10.0 ** n:g} x the field: a unit mistake ({words})')
        elif scales_checked:
            for ax, kk in zip(fx.AXIS_NAMES, k):
                if kk <= 0:
                    out.append(Note(
                        f'sensor {j}: scale k{ax} = {kk:+.3f} is negative: the {ax} axis reads '
                        'reversed; refit to record it as an axis map', 'parameters', j))
                    continue
                n = _unit_decade(kk)
                if n is not None:
                    flag(j, f'sensor {j}: scale k{ax} = {kk:.4g}: the {ax} readings are '
                            f'{kk:.3g} x the field: a unit mistake '
                            f'({UNIT_WORDS.get(n, "another unit")})')
                elif abs(kk - 1) > SCALE_FAR:
                    flag(j, f'sensor {j}: scale k{ax} = {kk:.3f}, far from 1 (real gains are '
                            f'within {SCALE_FAR:.0%}): a gain or range setting other than the '
                            'one the readings were converted with (an HMC5883L at 820 LSB/G '
                            'converted at 1090 gives 0.75), or a coil or channel with the '
                            'wrong gain')
        deg = np.degrees(np.abs(no))
        if deg.max() > ANGLE_WARN_DEG:
            names = ('psi', 'varphi', 'theta')
            worst = int(np.argmax(deg))
            flag(j, f'sensor {j}: non-orthogonality {names[worst]} = {deg[worst]:.1f} deg: '
                    'real sensor axes are perpendicular to within a degree or so; an element '
                    "tilted on its board, one axis picking up another's signal (crosstalk, a "
                    'shared return wire), or attitudes too few to separate the angle from the '
                    'scales')
        if np.degrees(mis) > ANGLE_WARN_DEG:
            flag(j, f'sensor {j}: turned by {np.degrees(mis):.1f} deg relative to sensor 1 '
                    '(misalignment): a mounting a few degrees off its drawing (a bracket, a '
                    'loose screw, a board mounted askew); the correction turns it into sensor '
                    "1's frame and stays right, but the array's geometry assumes aligned "
                    'sensors')
        for ax, o, r in zip(fx.AXIS_NAMES, cal.offset(j), np.abs(raw[j - 1]).max(axis=0)):
            if abs(o) > r:
                flag(j, f'sensor {j}: offset b{ax} = {o:+.0f} nT lies beyond every {ax} '
                        f'reading (|reading| <= {r:.0f} nT): the centre of the readings is '
                        'outside what the sensor measured: the attitudes cover too little of '
                        'the sphere to place it (rotate further, or --constrained), or the '
                        'readings are clipped')
    return out
