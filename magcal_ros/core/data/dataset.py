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

"""In-memory form of a recording of an S-sensor array (the wide CSV of docs/design.md §1)."""
from dataclasses import dataclass, field, replace

from magcal_ros.core.effects import raw_rate, SensorContext
import numpy as np

#: the per-epoch arrays of a Dataset and the axis of their epochs
EPOCH_AXES = {'t': 0, 'raw': 1, 'temp': 1, 'ref_total': 0, 'ref_vec': 0, 'angle_deg': 0,
              'plane': 0, 'attitude': 0, 'rate': 1}


@dataclass
class Dataset:
    """Samples of S sensors taken at common epochs (units: s, nT, degC)."""

    t: np.ndarray                               # (N,) s, non-decreasing
    raw: np.ndarray                             # (S, N, 3) nT, sensor axes; 0 is sensor 1
    temp: np.ndarray | None = None              # (S, N) degC (nan where a sensor has none)
    ref_total: np.ndarray | None = None         # (N,) reference field magnitude, nT
    ref_vec: np.ndarray | None = None           # (N, 3) reference field vector, nT (paper 002)
    angle_deg: np.ndarray | None = None         # (N,) turntable angle, deg (paper 000)
    plane: np.ndarray | None = None             # (N,) str, horizontal sensor plane 'xy'/'xz'
    aux: dict = field(default_factory=dict)     # 'aux_<name>' -> (N,), own units
    meta: dict = field(default_factory=dict)    # free-form provenance
    #: (N, 4) body-to-world unit quaternions (qw, qx, qy, qz), Hamilton, scalar first (CSV
    #: att_qw..att_qz); the world frame (NED or ENU) is the user's
    attitude: np.ndarray | None = None
    #: (S, N, 3) d(raw)/dt, nT/s, of the full-rate record when these epochs are a sample of it
    #: (:mod:`magcal_ros.core.data.reduce`); None: from these epochs
    rate: np.ndarray | None = field(default=None, repr=False)
    #: (whole Dataset, (N,) int positions in it) of a :meth:`subset` (a lag filter's record)
    origin: tuple | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        self.t = np.asarray(self.t, float)
        self.raw = np.asarray(self.raw, float)
        self.raw = self.raw[None] if self.raw.ndim == 2 else self.raw
        if self.raw.ndim != 3 or self.raw.shape[2] != 3:
            raise ValueError(f'raw must have shape (S, N, 3), got {self.raw.shape}')
        if self.raw.shape[1] != self.t.shape[0]:
            raise ValueError(f'raw has {self.raw.shape[1]} samples but t has {self.t.shape[0]}')
        if self.attitude is not None:
            from magcal_ros.core.geometry.attitude import check_quaternions
            self.attitude = check_quaternions(self.attitude, self.t)
        self._att_matrix = None

    @property
    def n_sensors(self):
        """Return the number of sensors S."""
        return self.raw.shape[0]

    @property
    def n_samples(self):
        """Return the number of epochs N."""
        return self.raw.shape[1]

    def context(self, j):
        """Return the :class:`SensorContext` of sensor ``j`` (1-based), d(raw)/dt in nT/s."""
        rate = raw_rate(self.raw[j - 1], self.t) if self.rate is None else self.rate[j - 1]
        temp = None if self.temp is None else self.temp[j - 1]
        temp = temp if temp is not None and np.isfinite(temp).any() else None
        ctx = SensorContext(t=self.t, temp=temp, aux=dict(self.aux), raw_rate=rate,
                            attitude=self.attitude_matrix())
        if self.origin is not None:
            whole, pos = self.origin
            wt = None if whole.temp is None else whole.temp[j - 1]
            ctx.parent = SensorContext(t=whole.t, temp=wt, aux=dict(whole.aux))
            ctx.index = pos
        return ctx

    def reference_magnitude(self, field_nt=None):
        """(N,) reference magnitude in nT: ``field_nt`` (scalar or (N,)) or ref_total."""
        if field_nt is not None:
            f = np.broadcast_to(np.asarray(field_nt, float), (self.n_samples,)).copy()
        elif self.ref_total is not None:
            f = np.asarray(self.ref_total, float)
        else:
            raise ValueError('no reference field magnitude: add a ref_total column, or give '
                             '--field-nt or --igrf')
        if not np.all(np.isfinite(f)) or np.any(f <= 0):
            raise ValueError('the reference field magnitude must be finite and positive')
        return f

    def attitude_matrix(self):
        """(N, 3, 3) body-to-world rotation matrices, or None without attitude."""
        if self.attitude is None:
            return None
        if self._att_matrix is None:
            from magcal_ros.core.geometry.attitude import quaternion_matrices
            self._att_matrix = quaternion_matrices(self.attitude)
        return self._att_matrix

    def subset(self, idx):
        """Return a new Dataset with the epochs ``idx`` (index array or boolean mask)."""
        idx = np.asarray(idx)
        at = np.flatnonzero(idx) if idx.dtype == bool else idx
        pos = np.arange(self.n_samples)[idx]
        origin = (self, pos) if self.origin is None else (self.origin[0], self.origin[1][pos])
        cols = {k: None if getattr(self, k) is None else np.take(getattr(self, k), at, axis=a)
                for k, a in EPOCH_AXES.items()}
        return replace(self, origin=origin, aux={k: np.take(v, at) for k, v in self.aux.items()},
                       meta=dict(self.meta), **cols)
