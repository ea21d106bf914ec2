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
The reference field magnitude F (nT) of a fit.

A number or the data's ``ref_total`` column
(:meth:`magcal_ros.core.data.dataset.Dataset.reference_magnitude`), the IGRF (ppigrf), or the
data themselves (shape only).  A reference *vector* is paper 002's
(:mod:`magcal_ros.core.papers.reference_vector`).
"""
import datetime

from magcal_ros.core.papers.ellipsoid import fit_ellipsoid
import numpy as np


def igrf_field(lat_deg, lon_deg, alt_km, date):
    """
    (total intensity nT, inclination deg, positive down) of the IGRF at a place and date.

    ``lat_deg``, ``lon_deg`` geodetic, deg; ``alt_km`` above the ellipsoid; ``date``
    'YYYY-MM-DD' or a datetime.date.
    """
    import ppigrf
    if isinstance(date, str):
        try:
            date = datetime.datetime.strptime(date, '%Y-%m-%d')
        except ValueError:
            raise ValueError(f'--igrf date must be YYYY-MM-DD, got {date!r}') from None
    elif isinstance(date, datetime.date) and not isinstance(date, datetime.datetime):
        date = datetime.datetime(date.year, date.month, date.day)
    if not (-90 <= lat_deg <= 90 and -360 <= lon_deg <= 360):
        raise ValueError(f'latitude/longitude out of range: {lat_deg}, {lon_deg}')
    be, bn, bu = (float(np.ravel(x)[0]) for x in ppigrf.igrf(lon_deg, lat_deg, alt_km, date))
    total = float(np.sqrt(be ** 2 + bn ** 2 + bu ** 2))
    return total, float(np.degrees(np.arctan2(-bu, np.hypot(be, bn))))


def auto_magnitude(raw):
    """
    Magnitude for data without any reference: mean radius of sensor 1's ellipsoid, nT.

    raw (N, 3) nT.  The absolute scale is then not observable: only the shape is corrected.
    """
    radii = np.linalg.norm(np.asarray(raw, float) - fit_ellipsoid(raw, 1.0).b, axis=1)
    return float(np.median(radii))


#: where a node's reference magnitude comes from (``field_source``)
FIELD_SOURCES = ('constant', 'igrf', 'shape')


def site_field_reference(source, field_nt=None, lat_deg=None, lon_deg=None, alt_m=0.0,
                         date=None, raw=None):
    """
    Return the reference magnitude and its ``field_reference`` record, as a node sets it.

    ``source``: 'constant' (``field_nt``, nT), 'igrf' (:func:`igrf_field` at ``lat_deg``,
    ``lon_deg`` deg, ``alt_m`` m, ``date`` 'YYYY-MM-DD'), 'shape' (:func:`auto_magnitude` of
    sensor 1's ``raw`` (N, 3) nT) or 'shape-planar' (a turn about one axis).  Returns (F nT,
    the calibration file's ``field_reference``); ValueError naming what is missing.
    """
    if source == 'constant':
        f = float(field_nt)
        return f, {'kind': 'constant', 'magnitude_nt': f}
    if source == 'igrf':
        if lat_deg is None or lon_deg is None or not date:
            raise ValueError('field_source igrf needs site_latitude_deg, site_longitude_deg '
                             'and site_date (YYYY-MM-DD)')
        f, inc = igrf_field(float(lat_deg), float(lon_deg), float(alt_m) / 1000.0, date)
        return f, {'kind': 'igrf', 'lat_deg': float(lat_deg), 'lon_deg': float(lon_deg),
                   'alt_km': float(alt_m) / 1000.0, 'date': str(date), 'magnitude_nt': f,
                   'inclination_deg': inc}
    if source == 'shape':
        f = auto_magnitude(raw)
        return f, {'kind': 'auto (mean radius, shape-only)', 'magnitude_nt': f}
    if source == 'shape-planar':
        # a turn about one axis: no ellipsoid, a circle and the mean along the axis
        from magcal_ros.core.geometry.turn import planar_magnitude, turn_axis
        f = planar_magnitude(raw, turn_axis(raw))
        return f, {'kind': 'auto (planar: in-plane radius and mean along the axis, '
                           'shape-only)', 'magnitude_nt': f}
    raise ValueError(f'field_source must be one of {FIELD_SOURCES}, got {source!r}')
