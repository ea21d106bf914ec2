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
Unit constants and conversions shared by every layer (pure numpy, no rclpy).

The library works in nT, s and degC; ROS messages carry SI units (T, T/m, REP 103), converted
in :mod:`magcal_ros.ros.conversions` with these helpers.
"""

import numpy as np

#: Nanotesla per tesla.
NT_PER_T = 1e9


def nt_to_t(value_nt):
    """Convert nT (or nT/m) of any shape to a float64 array of the same shape in T (or T/m)."""
    return np.asarray(value_nt, dtype=np.float64) / NT_PER_T


def t_to_nt(value_t):
    """Convert T (or T/m) of any shape to a float64 array of the same shape in nT (or nT/m)."""
    return np.asarray(value_t, dtype=np.float64) * NT_PER_T


# -- field units of user data (issue 10: gauss, uT or T read as nT) ----------------------------

#: nanotesla per unit of a field column (``--unit``)
UNITS_NT = {'nT': 1.0, 'uT': 1e3, 'mG': 100.0, 'G': 1e5, 'gauss': 1e5, 'T': 1e9}
#: magnitude of the geomagnetic field at the Earth's surface, nT (IGRF: ~22 000 to ~67 000)
GEOMAGNETIC_RANGE_NT = (20000.0, 70000.0)
#: readings outside this range are not a geomagnetic field in nT.  Wide on purpose: the units
#: differ by 10x or more, while an uncalibrated sensor that fits no sphere may add a hard-iron
#: offset of several times the field (6x measured on a QMC5883L)
PLAUSIBLE_RANGE_NT = (5000.0, 500000.0)
#: the readings and a given reference magnitude may differ by at most this factor
REFERENCE_RATIO = 8.0


def field_magnitude_estimate(raw):
    """
    Typical field magnitude, nT, seen by one sensor's uncalibrated ``raw`` (N, 3) nT.

    The radius of the least-squares sphere |x - c|^2 = r^2 through the readings (a hard-iron
    offset does not count), or the median |x| when they determine no sphere (one attitude,
    rotation about one axis).
    """
    x = np.asarray(raw, float)
    x = x[np.all(np.isfinite(x), axis=1)]
    med = float(np.median(np.linalg.norm(x, axis=1))) if len(x) else float('nan')
    if len(x) < 10:
        return med
    a = np.column_stack([2 * x, np.ones(len(x))])
    scale = np.abs(a).max(axis=0)
    scale[scale == 0] = 1.0
    sol = np.linalg.lstsq(a / scale, np.sum(x ** 2, axis=1), rcond=None)[0] / scale
    r2 = sol[3] + sol[:3] @ sol[:3]
    if not r2 > 0:
        return med
    r = float(np.sqrt(r2))
    # the sphere is determined only when the readings extend in all three directions by a
    # good fraction of its radius (a full sphere: ~0.58 r, 0.1 median |x| with a 6x offset;
    # one-axis rotations of the HMC5883L recordings 0.01-0.06 median |x|, static ones 0.003)
    spread = np.sqrt(max(np.linalg.eigvalsh(np.cov(x.T))[0], 0.0))
    return r if spread > 0.15 * r and spread > 0.05 * med else med


def units_that_fit(value_nt):
    """Units in which the number ``value_nt`` (read as nT) would be a geomagnetic field."""
    lo, hi = GEOMAGNETIC_RANGE_NT
    return [u for u, k in UNITS_NT.items() if u != 'gauss' and lo <= value_nt * k <= hi]


def _looks(value_nt):
    units = units_that_fit(value_nt)
    return (f'the numbers look like {units[0]} (give --unit {units[0]})' if units else
            'they are no geomagnetic field in any unit (nT, uT, mG, G, T)')


def check_field_units(raw, reference_nt=None, reference_name='the reference'):
    """
    Refuse readings or a reference magnitude that are not a geomagnetic field in nT.

    ``raw`` (S, N, 3) nT (after ``--unit``); ``reference_nt`` nT (None: the readings are
    judged against the geomagnetic range), given as ``reference_name`` (named in the
    message). Raises ValueError, one line: which numbers, how large, which unit they look like.
    """
    mags = [field_magnitude_estimate(r) for r in np.asarray(raw, float)]
    m = float(np.nanmedian(mags))
    if not np.isfinite(m):
        return
    lo, hi = PLAUSIBLE_RANGE_NT
    in_range = lo <= m <= hi
    if reference_nt is None:
        if not in_range:
            raise ValueError(
                f'the readings have a field magnitude of about {m:.4g} nT, not a geomagnetic '
                f'field ({GEOMAGNETIC_RANGE_NT[0]:.0f}-{GEOMAGNETIC_RANGE_NT[1]:.0f} nT): '
                + _looks(m))
        return
    f = float(reference_nt)
    ratio = m / f if f > 0 else np.inf
    if 1.0 / REFERENCE_RATIO <= ratio <= REFERENCE_RATIO:
        return
    if in_range:
        raise ValueError(
            f'{reference_name} is {f:.4g} nT but the readings have a field magnitude of about '
            f'{m:.0f} nT: {reference_name} must be in nT'
            + (f' (it looks like {units_that_fit(f)[0]}: {f * UNITS_NT[units_that_fit(f)[0]]:.0f}'
               ' nT)' if units_that_fit(f) else ''))
    raise ValueError(
        f'the readings have a field magnitude of about {m:.4g} nT and {reference_name} is '
        f'{f:.4g} nT: ' + _looks(m))


#: the unit of an auxiliary channel, by the ending of its name (the vehicle logs' channels,
#: docs/design.md §1): the first match wins
CHANNEL_UNITS = (('_current', 'A'), ('_voltage', 'V'), ('_power', 'W'), ('_temp', 'degC'),
                 ('_throttle', '1'))


def channel_unit(name):
    """Return the unit of aux channel ``name`` by its ending (:data:`CHANNEL_UNITS`), or None."""
    low = str(name).lower()
    return next((unit for end, unit in CHANNEL_UNITS if low.endswith(end)), None)


def coupling_unit(unit, label):
    """Return ``unit`` with the channel unit of ``label`` put in (``nT/unit``: ``nT/A``)."""
    if 'unit' not in unit:
        return unit
    import re
    found = (channel_unit(name) for name in re.findall(r'aux_[A-Za-z0-9_]+', str(label)))
    ch = next((c for c in found if c is not None), None)
    return unit if ch is None else unit.replace('unit', ch)
