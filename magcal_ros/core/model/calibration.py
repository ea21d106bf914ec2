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

"""A fitted model for live correction: :class:`Calibration` (docs/design.md §4)."""
from magcal_ros.core import effects as fx
import numpy as np


class Calibration:
    """A fitted model for live correction: ``params``, ``stderr`` (P,), ``sigma_nt`` (S,) nT."""

    def __init__(self, model, params, stderr=None, sigma_nt=None):
        self.model = model
        self.params = np.asarray(params, float)
        self.stderr = np.zeros_like(self.params) if stderr is None else np.asarray(stderr)
        self.sigma_nt = (np.full(model.n_sensors, np.nan) if sigma_nt is None
                         else np.asarray(sigma_nt, float))
        #: (K, K) covariance of the array-wide parameters (site gradient), when known
        self.array_covariance = None
        #: frame of the site gradient: 'world' or site_gradient.FIELD_ALIGNED
        self.site_frame = 'world'
        self._a_inv = [np.linalg.inv(model.matrix(j, self.params))
                       for j in range(1, model.n_sensors + 1)]

    @property
    def n_sensors(self):
        """Return the number of sensors."""
        return self.model.n_sensors

    def matrix(self, j):
        """(3, 3) forward linear map A_j of sensor j."""
        return self.model.matrix(j, self.params)

    def correction_matrix(self, j):
        """(3, 3) A_j^-1: corrected = A_j^-1 (raw - offset - driven)."""
        return self._a_inv[j - 1].copy()

    def offset(self, j):
        """Return the (3,) nT constant offset of sensor j (its ``Effect.constant`` effects)."""
        out = np.zeros(3)
        ctx = fx.SensorContext(t=np.zeros(1))
        for eff, sl in zip(self.model.effects[j - 1], self.model.slices[j - 1]):
            if eff.kind != 'linear' and eff.constant:
                out = out + eff.contribution(self.params[sl], ctx, np.zeros((1, 3)))[0]
        return out

    def intrinsic_and_rotation(self, j):
        """
        (C^-1 (3, 3) upper triangular, R (3, 3)): A_j^-1 = R C^-1 M^T (paper 004 eq. 5, 14).

        M is the axis map (``model.axis_map(j)``); R turns sensor j's frame into sensor 1's.
        """
        u, q = fx.rq_positive(self.model.axis_map(j).T @ self.matrix(j))
        return np.linalg.inv(u), q.T

    def site_gradient(self):
        """(G_w (3, 3), stderr (3, 3)) nT/m or None; gzz's stderr nan without array_covariance."""
        from magcal_ros.core.geometry.tensor import gradient_from_fit
        cov = np.diag(self.stderr ** 2)
        cols = self.model.array_cols
        if self.array_covariance is not None:
            cov[np.ix_(cols, cols)] = self.array_covariance
        out = gradient_from_fit(self.model, self.params, cov)
        if out is not None and self.array_covariance is None:
            out[1][2, 2] = np.nan
        return None if out is None else out[:2]

    def array_shift(self, j, ctx):
        """(N, 3) nT field at sensor j minus the centre field (zero without array effects)."""
        return self.model.array_shift(j, self.params, ctx)

    def driven_effects(self, j):
        """Return the labels of sensor j's additive effects evaluated per sample."""
        return [e.label for e in self.model.effects[j - 1]
                if e.kind != 'linear' and not e.constant]

    def signals(self, j):
        """Driving signals the effects of sensor j read (``Effect.signals``), in order."""
        return list(dict.fromkeys(s for eff in self.model.effects[j - 1] for s in eff.signals))

    def correct(self, j, raw, ctx=None):
        """Corrected field (N, 3) or (3,) nT of sensor j's ``raw`` (ctx: for driven effects)."""
        raw = np.asarray(raw, float)
        one = raw.ndim == 1
        raw2 = raw[None] if one else raw
        if ctx is None:
            if self.driven_effects(j):
                raise ValueError(f'sensor {j} has driven effects {self.driven_effects(j)}: '
                                 'pass their signals in ctx')
            ctx = fx.SensorContext(t=np.zeros(len(raw2)))
        out = self.model.correct(j, self.params, raw2, ctx, a_inv=self._a_inv[j - 1])
        return out[0] if one else out

    def correct_dataset(self, data):
        """(S, N, 3) nT corrected readings of every sensor of a Dataset."""
        return np.stack([self.correct(j, data.raw[j - 1], data.context(j))
                         for j in range(1, self.n_sensors + 1)])
