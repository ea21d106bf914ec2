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

"""What the vehicle-log front-ends fill (:class:`VehicleLog`) and :mod:`~.vehicle` reads."""
from dataclasses import dataclass, field

import numpy as np

#: slow channels (temperatures, voltages) are read at most at this rate, Hz
SLOW_RATE_HZ = 10.0
#: nT per milligauss (ArduPilot's compass unit) and per gauss (PX4's)
NT_PER_MGAUSS = 100.0
NT_PER_GAUSS = 1e5

ULOG_MAGIC = b'ULog\x01\x12\x35'
DATAFLASH_MAGIC = b'\xa3\x95'


class VehicleLogError(ValueError):
    """A vehicle log that cannot be used; the message says what and what to do."""


@dataclass
class Stream:
    """One timed stream of a log: ``t`` (M,) s, ``v`` (M,) or (M, k), ``name`` its source."""

    t: np.ndarray
    v: np.ndarray
    name: str = ''


@dataclass
class VehicleLog:
    """
    What a format front-end read.

    ``compasses`` :class:`Stream` of (M, 3) raw body-frame nT, compass 1 first;
    ``compass_temps`` (M,) degC Streams or None; ``attitude`` a Stream of (M, 4) body-to-NED
    (w, x, y, z) or None; ``aux`` {name: Stream (M,)}, ``aux_units`` {name: unit}; ``gps``
    (:func:`gps_site`); ``onboard`` a dict per compass; ``info`` more ``meta``; ``warnings``.
    """

    source_format: str
    compasses: list = field(default_factory=list)
    compass_temps: list = field(default_factory=list)
    attitude: Stream | None = None
    attitude_source: str | None = None
    aux: dict = field(default_factory=dict)
    aux_units: dict = field(default_factory=dict)
    gps: dict | None = None
    onboard: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def add_aux(self, name, t, v, unit, source):
        """Add channel ``name`` (times ``t`` (M,) s, values ``v`` (M,)) when it has data."""
        t, v = np.asarray(t, float), np.asarray(v, float)
        ok = np.isfinite(t) & np.isfinite(v)
        if ok.sum() < 1:
            return
        self.aux[name] = Stream(t[ok], v[ok], source)
        self.aux_units[name] = unit


def gps_site(lat_deg, lon_deg, alt_m, dates):
    """
    ``{lat_deg, lon_deg, alt_km, date, fixes}`` of good (3-D) GPS fixes, or None.

    ``lat_deg``, ``lon_deg`` (deg), ``alt_m`` (m), ``dates`` ('YYYY-MM-DD' or '') (M,): the
    median position and the first known date; None without a position and a date.
    """
    lat, lon, alt = (np.asarray(a, float) for a in (lat_deg, lon_deg, alt_m))
    ok = np.isfinite(lat) & np.isfinite(lon) & (np.abs(lat) <= 90) & (np.abs(lon) <= 360) & \
        ~((lat == 0) & (lon == 0))
    if not ok.any():
        return None
    date = next((d for d, k in zip(dates, ok) if k and d), None)
    if date is None:
        return None
    altk = alt[ok]
    altk = altk[np.isfinite(altk)]
    return {'lat_deg': float(np.median(lat[ok])), 'lon_deg': float(np.median(lon[ok])),
            'alt_km': float(np.median(altk)) / 1000.0 if len(altk) else 0.0, 'date': date,
            'fixes': int(ok.sum())}
