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
Live correction of an array, one sample at a time (no ROS: used by the corrector node).

:class:`LiveCorrector` holds the calibration made ready per sensor (every matrix computed
once: a sample costs a few 3x3 products), the latest driving signals, the set matcher and
the gradient operator.  Also :class:`ResidualMonitor` (``calibration/residual``) and
:class:`SampleBuffer` (the sets collected for a fit).  Units: nT, nT/s, nT/m, s, degC.
"""
from collections import deque

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.data.noise import noise_floor
from magcal_ros.core.effects import raw_rate, SensorContext, SIGNALS
from magcal_ros.core.effects.safety import EffectError
from magcal_ros.core.geometry.tensor import TENSOR_MAP, tensor_operator
from magcal_ros.core.live.sync import epoch_times, StampMatcher
import numpy as np

#: consecutive raw samples further apart than this give no field-rate estimate, s
MAX_RATE_GAP_S = 1.0
#: arrivals per stream used to estimate its sample period (field-rate effect)
PERIOD_WINDOW = 200
#: arrivals needed before the sample period (and so the field rate) is estimated
_MIN_ARRIVALS = 11
#: chance that a correctly paired set of Gaussian noise fails :meth:`LiveCorrector.pairing_chi2`
PAIRING_FALSE_ALARM = 1e-6


class MissingSignal(Exception):
    """A driven effect of the calibration has no live signal yet (the message says which)."""


def _waiting(j, name):
    """Why the correction of sensor j waits for the signal ``name``."""
    if name == 'temperature':
        return (f'sensor {j}: waiting for sensor{j}/temperature (the calibration has an '
                'effect that reads the temperature)')
    if name == 'field_rate':
        return f'sensor {j}: field rate needs three consecutive samples'
    if name.startswith('aux_'):
        return (f'sensor {j}: waiting for auxiliary channel {name} (topic {name[4:]} named in '
                'aux_topics)')
    return f'sensor {j}: the calibration needs the signal {name!r}, which is not received'


def calibration_covariance_nt2(cal, j, field_nt):
    """
    (3, 3) covariance of sensor j's corrected field from the calibration's uncertainty, nT^2.

    A parameter off by its standard uncertainty makes c = A'^-1 (raw - o') differ from b by
    M b + d (M = A'^-1 A - I, d = A'^-1 (o - o')); over directions uniform on the sphere of
    radius ``field_nt`` that is M M^T F^2 / 3 + d d^T, summed over the sensor's linear and
    offset parameters (correlations and driven effects left out).  ``j`` 1-based; zeros
    without uncertainties.
    """
    from magcal_ros.core.model.calibration import Calibration
    model = cal.model
    a, o = cal.matrix(j), cal.offset(j)
    out = np.zeros((3, 3))
    for sl in model.slices[j - 1]:
        for k in range(sl.start, sl.stop):
            se = float(cal.stderr[k]) if k < len(cal.stderr) else 0.0
            if not (np.isfinite(se) and se > 0):
                continue
            p = cal.params.copy()
            p[k] += se
            moved = Calibration(model, p)
            a_inv = moved.correction_matrix(j)
            m = a_inv @ a - np.eye(3)
            d = a_inv @ (o - moved.offset(j))
            out += m @ m.T * field_nt ** 2 / 3.0 + np.outer(d, d)
    return _symmetric(out)


def _symmetric(c):
    """Return the symmetric part of a square matrix ``c`` (rounding makes products asymmetric)."""
    return 0.5 * (c + c.T)


class _Sensor:
    """The calibration of one sensor made ready for per-sample correction."""

    def __init__(self, cal, j, field_nt=None):
        self.a_inv = cal.correction_matrix(j)
        self.offset = cal.offset(j)
        self.needs = set(cal.signals(j)) - {'time'}
        self.driven = bool(cal.driven_effects(j))
        sigma = float(cal.sigma_nt[j - 1])
        self.cal_cov_nt2 = (calibration_covariance_nt2(cal, j, field_nt)
                            if field_nt else np.zeros((3, 3)))
        #: sigma^2 A^-1 A^-T, nT^2 (None: no noise estimate)
        self.cov_nt2 = (_symmetric(sigma ** 2 * self.a_inv @ self.a_inv.T)
                        if np.isfinite(sigma) and sigma > 0 else None)
        self.recent = deque(maxlen=3)    # (t s, raw (3,) nT) of the latest samples
        self.arrivals = deque(maxlen=PERIOD_WINDOW)


class LiveCorrector:
    """
    A calibration made ready to correct live samples of every sensor of an array.

    ``cal`` a Calibration (effect code raising in it: an EffectError naming the effect);
    ``n_sensors`` the calibration's count (else ValueError); ``positions_m`` (S, 3) m in the
    array frame (without: no gradient, :attr:`no_gradient_reason`); ``stamp_tolerance_s`` of
    the :class:`~magcal_ros.core.live.sync.StampMatcher`, s; ``check_pairing``: check every
    set from the data (:meth:`pairing_chi2`) and re-pair a shifted stream at once;
    ``field_nt`` (nT): :meth:`published_covariance_nt2` adds
    :func:`calibration_covariance_nt2`.
    """

    def __init__(self, cal, n_sensors, positions_m=None, stamp_tolerance_s=0.005,
                 check_pairing=True, field_nt=None):
        if cal.n_sensors != n_sensors:
            raise ValueError(f'the calibration is for {cal.n_sensors} sensors but this '
                             f'corrector handles {n_sensors} (n_sensors)')
        self.cal = cal
        self.n_sensors = n_sensors
        try:
            self._sensors = [_Sensor(cal, j, field_nt) for j in range(1, n_sensors + 1)]
        except Exception as exc:           # noqa: B902 -- effect code may raise anything
            raise EffectError(exc) from exc
        self.temp = np.full(n_sensors, np.nan)
        self.aux = {}
        self.matcher = StampMatcher(n_sensors, stamp_tolerance_s)
        #: (9, 3 S) stacked corrected fields (nT) to the row-major tensor (nT/m), or None
        self.gradient_op = None
        #: (9, 9) covariance of that tensor, (nT/m)^2; None: a sensor has no noise estimate
        self.gradient_cov_nt2 = None
        self.no_gradient_reason = self.positions_m = None
        #: redundant combinations the check tests (3 S - 8; 0: none), and the largest
        #: chi-square that passes (at :data:`PAIRING_FALSE_ALARM`)
        self.pairing_dof, self.pairing_threshold = 0, np.inf
        self._set_op = None            # (9 + dof, 3 S): the tensor, then K (pairing_chi2)
        self._checked = None           # (the fields last checked, their _set_op product)
        self.no_check_reason = ('sets are paired by stamps alone (check_pairing off)'
                                if not check_pairing else 'no gradient, no sets to check')
        if positions_m is None:
            self.no_gradient_reason = 'the calibration has no array geometry (positions_m)'
            return
        try:
            pos = np.asarray(positions_m, float)
            if pos.shape != (n_sensors, 3):
                raise ValueError(f'positions_m has shape {pos.shape}, expected ({n_sensors}, 3)')
            self.gradient_op = tensor_operator(pos)[3:]
            self.positions_m = pos
        except ValueError as exc:
            self.no_gradient_reason = f'no gradient: {exc}'
            return
        covs = [s.cov_nt2 for s in self._sensors]
        if all(c is not None for c in covs):
            block = np.zeros((3 * n_sensors, 3 * n_sensors))
            for k, c in enumerate(covs):
                block[3 * k:3 * k + 3, 3 * k:3 * k + 3] = c
            self.gradient_cov_nt2 = _symmetric(self.gradient_op @ block @ self.gradient_op.T)
            if check_pairing:
                k = pairing_operator(pos, block)
                self.pairing_dof = dof = len(k)
                if dof:
                    self._set_op = np.vstack([self.gradient_op, k])
                    # = scipy.stats.chi2.isf, without importing scipy.stats (BENCHMARKS.md)
                    from scipy.special import chdtri
                    self.pairing_threshold = float(chdtri(dof, PAIRING_FALSE_ALARM))
                    self.matcher.misfit = self.pairing_chi2
                    self.matcher.threshold = self.pairing_threshold
        if check_pairing:
            self.no_check_reason = None if self.pairing_dof else (
                'sets are paired by stamps alone: ' + (
                    'a sensor of the calibration has no noise estimate'
                    if self.gradient_cov_nt2 is None
                    else f'{n_sensors} sensors leave no redundancy to check a set'))

    @property
    def needs_temperature(self):
        """Tell whether an effect of the calibration is driven by the sensor temperature."""
        return any('temperature' in s.needs for s in self._sensors)

    def sensor_frames(self):
        """
        Pose of each sensor's frame in the array frame, from the calibration and geometry.

        Sensor j's frame is its orthogonalised axes (C_j^-1 raw, paper 004 eq. 5), R_j
        rotates it into the array frame (eq. 14).  Returns [(R_j (3, 3), position (3,) m)]
        per sensor; [] without geometry.
        """
        if self.positions_m is None:
            return []
        return [(self.cal.intrinsic_and_rotation(j)[1], self.positions_m[j - 1].copy())
                for j in range(1, self.n_sensors + 1)]

    def site_shift(self, quaternion):
        """
        (S, 3) nT shift of every sensor by the calibration's site gradient, or None.

        R^T G_w R r_j (docs/site_gradient.md) at the attitude ``quaternion`` (4,) (qw, qx, qy,
        qz, body-to-world); EffectError if the effect's code raises.
        """
        if self.cal.site_gradient() is None:
            return None
        from magcal_ros.core.geometry.attitude import quaternion_matrices
        ctx = SensorContext(t=np.zeros(1),
                            attitude=quaternion_matrices(np.asarray(quaternion, float)[None]))
        try:
            return np.stack([self.cal.array_shift(j, ctx)[0]
                             for j in range(1, self.n_sensors + 1)])
        except Exception as exc:           # noqa: B902 -- effect code may raise anything
            raise EffectError(exc) from exc

    def linear(self, j):
        """
        (A_j^-1 (3, 3), offset (3,) nT) when sensor j's correction is that alone, else None.

        A_j^-1 (raw - o_j) holds in any unit (a caller may apply it in tesla); no field-rate
        state is kept on that path.
        """
        s = self._sensors[j - 1]
        return None if s.driven else (s.a_inv.copy(), s.offset.copy())

    def published_covariance_nt2(self, j):
        """
        (3, 3) covariance a corrected sample of sensor j is published with, nT^2.

        The noise's sigma^2 A^-1 A^-T plus :func:`calibration_covariance_nt2` (with
        ``field_nt``); None without a noise estimate.
        """
        s = self._sensors[j - 1]
        return None if s.cov_nt2 is None else s.cov_nt2 + s.cal_cov_nt2

    def set_temperature(self, j, temp_c):
        """Latest temperature of sensor j (1-based), degC."""
        self.temp[j - 1] = temp_c

    def set_aux(self, column, value):
        """Latest value of the auxiliary channel ``column`` (``aux_<name>``)."""
        self.aux[column] = float(value)

    def correct(self, j, t, raw):
        """
        Correct one finite raw sample of sensor j and remember it for the field rate.

        ``j`` 1-based, ``t`` its stamp s, ``raw`` (3,) nT; returns the corrected field (3,) nT
        in the array frame.  Raises :class:`MissingSignal` while a driven effect has no live
        signal (temperature, auxiliary channel, the field rate before the stream's period is
        known), EffectError when an effect's code raised (no correction).
        """
        s = self._sensors[j - 1]
        s.recent.append((t, raw))
        s.arrivals.append(t)
        if not s.driven:
            return s.a_inv @ (raw - s.offset)
        rate = self._rate(s) if 'field_rate' in s.needs else None
        temp = self.temp[j - 1]
        ctx = SensorContext(
            t=np.array([t]), temp=np.array([temp]) if np.isfinite(temp) else None,
            aux={k: np.array([v]) for k, v in self.aux.items()},
            raw_rate=None if rate is None else rate[None])
        for name in sorted(s.needs):
            if not (name in SIGNALS or name.startswith('aux_')) or not ctx.has(name):
                raise MissingSignal(_waiting(j, name))
        try:
            return self.cal.correct(j, raw, ctx)
        except Exception as exc:           # noqa: B902 -- effect code may raise anything
            raise EffectError(exc, where=f'the correction of sensor {j}') from exc

    @staticmethod
    def _rate(s):
        """
        Return d(raw)/dt (3,) nT/s of the newest sample, or None.

        :func:`~magcal_ros.core.effects.raw_rate` on the last three samples, the period the
        mean over the last :data:`PERIOD_WINDOW` arrivals (stamps of one read are equal).
        """
        if (len(s.recent) < 3 or len(s.arrivals) < _MIN_ARRIVALS
                or np.diff([t for t, _ in s.recent]).max() > MAX_RATE_GAP_S):
            return None
        period = (s.arrivals[-1] - s.arrivals[0]) / (len(s.arrivals) - 1)
        rate = raw_rate(np.stack([r for _, r in s.recent]), period=period)
        return None if rate is None else rate[-1]

    def sets(self, j, t, field_nt):
        """
        Add a corrected sample of sensor j; return the sets of all sensors it completes.

        ``j``, ``t`` as for :meth:`correct`, ``field_nt`` (3,) nT its result.  Returns
        [(stamp of the set s, the S corrected fields (3,) nT)], oldest first.
        """
        return [(t_set, fields) for _, t_set, fields in self.matcher.add(j - 1, t, field_nt)]

    def pairing_chi2(self, fields_nt):
        """
        Chi-square of the S corrected fields of a set as the samples of one epoch.

        A set of one epoch fits B(r) = B0 + G r, G symmetric traceless, to the noise: chi^2
        = |K b|^2 (:func:`pairing_operator`) has :attr:`pairing_dof` dof whatever the
        gradient; a sample of another epoch of a turning array adds a field change no such G
        absorbs.  ``fields_nt``: S corrected fields (3,) nT, array frame; 0 without a check.
        """
        if self._set_op is None:
            return 0.0
        y = self._set_op @ np.concatenate(fields_nt)
        self._checked = (fields_nt, y)
        z = y[9:]
        return float(z @ z)

    def gradients(self, j, t, field_nt):
        """
        Add a corrected sample of sensor j; return the tensors of the sets it completes.

        As :meth:`sets`, with the tensor (3, 3) nT/m in place of the fields; [] without
        geometry.
        """
        if self.gradient_op is None:
            return []
        out = []
        for t_set, fields in self.sets(j, t, field_nt):
            checked = self._checked         # the check's product holds the tensor
            g = (checked[1][:9] if checked is not None and checked[0] is fields
                 else self.gradient_op @ np.concatenate(fields))
            out.append((t_set, g.reshape(3, 3)))
        return out


def pairing_operator(positions_m, cov_nt2):
    """
    Whitened residual map of the set check: chi^2 of a set = |K b|^2.

    The residual of b = H theta + noise, theta = (B0, g_xx, g_xy, g_xz, g_yy, g_yz), in the
    noise metric: Sigma = L L^T, L^-1 H = Q R, Q_r the last 3 S - rank(H) columns of Q,
    K = Q_r^T L^-1.  ``positions_m`` (S, 3) m, ``cov_nt2`` (3 S, 3 S) nT^2 of the stacked
    corrected fields; returns K (3 S - rank(H), 3 S), 1/nT.
    """
    pos = np.asarray(positions_m, float)
    pos = pos - pos.mean(axis=0)
    # rows 3 k + i: B0_i + (G r_k)_i, G = TENSOR_MAP theta[3:] (+ 0.0: no -0.0)
    lin = np.einsum('ijq,kj->kiq', TENSOR_MAP.reshape(3, 3, 5), pos).reshape(-1, 5) + 0.0
    h = np.hstack([np.tile(np.eye(3), (len(pos), 1)), lin])
    chol = np.linalg.cholesky(cov_nt2)
    hw = np.linalg.solve(chol, h)
    rank = np.linalg.matrix_rank(hw)
    q, _ = np.linalg.qr(hw, mode='complete')
    return np.linalg.solve(chol.T, q[:, rank:]).T         # Q_r^T L^-1


#: a rolling residual above this multiple of its noise-only expectation: the calibration no
#: longer fits
RESIDUAL_WARN_RATIO = 1.5


class ResidualMonitor:
    """
    Residuals of the active calibration on live sets, and their ratio to the noise floor.

    Per set of corrected fields b_j (nT): the scalar residual ``|b_j| - F`` and the vector
    residual ``|b_j - mean_{k != j} b_k|``.  Their RMS over the last ``window`` sets is
    compared with the noise alone: f_j, the floor of each corrected series (:func:`noise_floor`),
    for the scalar, sqrt(3 (f_j^2 + sum_{k != j} f_k^2 / (S - 1)^2)) for the vector one
    (NaN for one sensor).

    ``field_nt``: reference magnitude F, nT; ``window``: sets in the rolling window.
    """

    def __init__(self, n_sensors, field_nt, window=1000):
        if n_sensors < 1:
            raise ValueError('the residual needs at least one sensor')
        self.n_sensors = n_sensors
        self.kinds = ('scalar', 'vector') if n_sensors > 1 else ('scalar',)
        self.field_nt = float(field_nt)
        self.window = int(window)
        self._fields = np.zeros((n_sensors, self.window, 3))
        self._scalar = np.zeros((n_sensors, self.window))
        self._vector = np.zeros((n_sensors, self.window))
        self.count = 0                                 # sets added

    def add(self, fields_nt):
        """
        Add one set of (S, 3) corrected fields, nT (in time order); return its residuals.

        Returns (scalar residual (S,) nT, signed; vector residual (S,) nT, a length).
        """
        b = np.asarray(fields_nt, float)
        s = self.n_sensors
        scalar = np.sqrt(np.einsum('ij,ij->i', b, b)) - self.field_nt
        others = (b.sum(axis=0)[None, :] - b) / max(s - 1, 1)         # mean of the others
        vector = np.sqrt(np.sum((b - others) ** 2, axis=1)) if s > 1 else np.full(1, np.nan)
        k = self.count % self.window
        self._fields[:, k], self._scalar[:, k], self._vector[:, k] = b, scalar, vector
        self.count += 1
        return scalar, vector

    def ratios(self, min_sets=50):
        """
        Return the rolling RMS residuals and their ratio to the noise-only expectation.

        {``scalar_rms_nt``, ``vector_rms_nt``, ``floor_nt`` (S,) nT, ``scalar_ratio``,
        ``vector_ratio`` (S,), ``sets``}; None with fewer than ``min_sets`` sets.
        """
        n = min(self.count, self.window)
        if n < max(min_sets, 14):
            return None
        order = (np.arange(self.count - n, self.count) % self.window)
        floor = noise_floor(self._fields[:, order])
        s = self.n_sensors
        f2 = floor ** 2
        vector_expected = (np.sqrt(3.0 * (f2 + (f2.sum() - f2) / (s - 1) ** 2)) if s > 1
                           else np.full(1, np.nan))
        scalar_rms = np.sqrt(np.mean(self._scalar[:, order] ** 2, axis=1))
        vector_rms = np.sqrt(np.mean(self._vector[:, order] ** 2, axis=1))
        with np.errstate(divide='ignore', invalid='ignore'):
            return {'sets': n, 'floor_nt': floor, 'scalar_rms_nt': scalar_rms,
                    'vector_rms_nt': vector_rms, 'scalar_ratio': scalar_rms / floor,
                    'vector_ratio': vector_rms / vector_expected}


class SampleBuffer:
    """
    Matched sample sets of S sensors spread evenly over the whole run, in flat memory.

    Not thread-safe.  At most ``capacity`` sets: when full, every other set held is dropped
    and from then on every 2nd set arriving is kept, then every 4th, ..., so the whole run's
    attitudes enter the calibration (:meth:`coverage`).

    ``capacity``: most sets kept (at least 2); ``aux_names``: auxiliary columns
    (``aux_<name>``); ``source``: ``meta['source']`` of the datasets it returns.
    """

    def __init__(self, n_sensors, capacity, aux_names=(), source='live (calibration_node)'):
        self.n_sensors = n_sensors
        self.source = source
        self.capacity = max(2, int(capacity))
        self.t = np.zeros(self.capacity)
        self.epoch = np.zeros(self.capacity, np.int64)
        self.raw = np.zeros((n_sensors, self.capacity, 3))
        self.temp = np.full((n_sensors, self.capacity), np.nan)
        self.aux = {a: np.full(self.capacity, np.nan) for a in aux_names}
        self.clear()

    def clear(self):
        """Forget all sets."""
        self.count = 0          # sets added since clear()
        self.n = 0              # sets held
        self.stride = 1         # every stride-th set arriving is kept
        self.t_first = self.t_last = None

    def __len__(self):
        return self.n

    def append(self, epoch, t, raw, temp, aux):
        """Add a set: epoch number, stamp t s, raw (S, 3) nT, temp (S,) degC (nan: none), aux."""
        k = self.count
        self.count += 1
        self.t_first = float(t) if self.t_first is None else self.t_first
        self.t_last = float(t)
        if not k % self.stride and self.n == self.capacity:
            self._thin()
        if k % self.stride:
            return
        i = self.n
        self.epoch[i] = epoch
        self.t[i] = t
        self.raw[:, i] = raw
        self.temp[:, i] = temp
        for name, arr in self.aux.items():
            arr[i] = aux.get(name, np.nan)
        self.n += 1

    def _thin(self):
        """Keep every other set held (the 1st, 3rd, ...) and every 2 x stride-th from now."""
        keep = np.arange(0, self.n, 2)
        m = len(keep)
        for arr in (self.epoch, self.t, *self.aux.values()):
            arr[:m] = arr[keep]
        for arr in (self.raw, self.temp):
            arr[:, :m] = arr[:, keep]
        self.n = m
        self.stride *= 2

    def coverage(self):
        """
        How much of the run the sets held stand for (JSON-ready).

        ``sets_held``, ``sets_received``, ``stride``, ``run_s`` (first to latest set, s),
        ``held_from_s`` / ``held_to_s`` (s after the first set), ``fraction_of_run``.
        """
        run = 0.0 if self.t_first is None else self.t_last - self.t_first
        out = {'sets_held': int(self.n), 'sets_received': int(self.count),
               'stride': int(self.stride), 'run_s': round(float(run), 3)}
        if self.n:
            lo = float(self.t[0] - self.t_first)
            hi = float(self.t[self.n - 1] - self.t_first)
            out.update(held_from_s=round(lo, 3), held_to_s=round(hi, 3),
                       fraction_of_run=round((hi - lo) / run, 4) if run > 0 else 1.0)
        return out

    def _order(self, max_sets=None):
        idx = np.arange(self.n)
        if max_sets is not None and self.n > max_sets:
            idx = idx[np.linspace(0, self.n - 1, max_sets).round().astype(int)]
        return idx

    def raw_view(self, max_sets=None):
        """(S, M, 3) nT raw readings, chronological, at most ``max_sets`` evenly spaced."""
        return self.raw[:, self._order(max_sets)]

    def epochs(self):
        """(N,) int epoch numbers of the buffered sets, chronological (a copy)."""
        return self.epoch[:self.n].copy()

    def stamps(self):
        """(N,) s stamps of the buffered sets as they arrived, chronological (a copy)."""
        return self.t[:self.n].copy()

    def dataset(self):
        """Return a :class:`Dataset` of the buffered sets in chronological order (copies)."""
        idx = self._order()
        temp = self.temp[:, idx]
        return Dataset(t=epoch_times(self.epoch[idx], self.t[idx]), raw=self.raw[:, idx].copy(),
                       temp=temp.copy() if np.isfinite(temp).any() else None,
                       aux=held_aux(self.aux, idx), meta={'source': self.source})


def held_aux(aux, idx):
    """
    Auxiliary columns at ``idx`` (those with a value), held before their first value arrived.

    ``aux``: {column: (C,) values, nan where none}; returns {column: (len(idx),)}.
    """
    out = {}
    for name, arr in aux.items():
        col = arr[idx]
        ok = np.isfinite(col)
        if ok.any():
            out[name] = np.where(ok, col, col[np.argmax(ok)])
    return out
