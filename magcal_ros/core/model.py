"""Composable calibration models of a magnetometer array and their maximum-likelihood fit.

A :class:`Model` is a list of effects per sensor (see :mod:`magcal_ros.core.effects`).
:func:`fit` estimates its parameters from rotation data in a uniform field:

1. closed-form start (paper 004 section 3): ellipsoid fit + Cholesky per sensor (eq. 8-13),
   orthogonal Procrustes into sensor 1's frame (eq. 14);
2. maximum-likelihood refinement of all sensors jointly with ``scipy.optimize.least_squares``.
   The noise is modelled on the raw readings: raw_jk = f_j(B_k) + e_jk, e ~ N(0, sigma_j^2 I),
   with the unknown field B_k of epoch k constrained to the reference magnitude |B_k| = F_k.
   B_k is a nuisance parameter, eliminated by variable projection: for given model
   parameters it is estimated from all sensors (a Gauss-Newton step on the sphere |B| = F_k),
   and the Jacobian of the model parameters is projected onto the complement of the
   nuisance directions (Golub-Pereyra / Kaufman).  The same projected Jacobian gives the
   parameter covariance (Cramer-Rao bound at the solution).

With one sensor, or with sensors that are not tied together by a misalignment term, this is
the usual scalar calibration (each sensor's own field estimate); with misalignment on the
other sensors the sensors share one field per epoch, which uses both the scalar constraint and
the inter-sensor vector consistency.
"""
from dataclasses import dataclass, field
import hashlib

import numpy as np
from scipy.optimize import least_squares

from magcal_ros.core import effects as fx
from magcal_ros.core.ellipsoid import fit_ellipsoid, procrustes_rotation
from magcal_ros.core.magnitude import reference_magnitude
from magcal_ros.core.noise import mad_sd
from magcal_ros.core.notes import Note

class DegenerateDataError(ValueError):
    """The data cannot determine the model: the message names what is missing."""


# -- model ----------------------------------------------------------------------------------

class Model:
    """Effects per sensor, with a flat parameter vector.

    Parameters
    ----------
    effects : list of list of Effect
        ``effects[j-1]`` are the effects of sensor j.
    array_effects : list of Effect, optional
        Effects with one set of parameters for the whole array (``scope = 'array'``, e.g.
        ``site_gradient``); their parameters follow those of the sensors in the vector.
    """

    def __init__(self, effects, array_effects=()):
        self.effects = [list(e) for e in effects]
        self.array_effects = list(array_effects)
        if self.array_effects and self.n_sensors == 4:
            from magcal_ros.core.tensor import cross_positions
            for eff in self.array_effects:
                if hasattr(eff, 'set_positions') and 'x1' not in eff.refs:
                    eff.set_positions(cross_positions(0.5))     # paper 004's cross
        self._layout()

    def _layout(self):
        self.slices = []
        self.sensor_slices = []
        i = 0
        for sensor_effects in self.effects:
            start = i
            row = []
            for eff in sensor_effects:
                row.append(slice(i, i + eff.n_params))
                i += eff.n_params
            self.slices.append(row)
            self.sensor_slices.append(slice(start, i))
        self.array_slices = []
        for eff in self.array_effects:
            self.array_slices.append(slice(i, i + eff.n_params))
            i += eff.n_params
        self.n_params = i

    @property
    def array_cols(self):
        """(K,) indices of the array-wide parameters in the parameter vector."""
        return np.concatenate([np.arange(sl.start, sl.stop) for sl in self.array_slices]
                              ).astype(int) if self.array_slices else np.zeros(0, int)

    def set_positions(self, positions):
        """Sensor positions (S, 3) m in the array frame, for the array-wide effects."""
        for eff in self.array_effects:
            if hasattr(eff, 'set_positions'):
                eff.set_positions(positions)

    @property
    def n_sensors(self):
        """Number of sensors S."""
        return len(self.effects)

    @classmethod
    def from_spec(cls, spec, n_sensors):
        """Build a model from a comma-separated spec (docs/design.md §2).

        ``base`` expands to offset, scale, nonorthogonality, misalignment; ``name@j``
        restricts an effect to sensor j; ``aux:<column>`` couples an auxiliary channel.
        Effects that do not exist on sensor 1 (``Effect.on_sensor1`` False: the
        misalignment, sensor 1 defines the array frame) are dropped there; linear effects
        are multiplied in the order of their ``Effect.linear_order``.
        """
        tokens = spec if isinstance(spec, (list, tuple)) else fx.split_spec(spec)
        tokens = [t.strip() for t in tokens if t.strip()]
        if not tokens:
            raise ValueError('empty model: give at least one effect, e.g. --model base')
        per_sensor = [[] for _ in range(n_sensors)]
        seen = [set() for _ in range(n_sensors)]
        array_effects = []
        for tok in tokens:
            # name(arguments)@j: a step time, a frequency, a channel (effects.parse_token)
            name, where = (tok.rsplit('@', 1) if tok.rfind('@') > tok.rfind(')')
                           else (tok, ''))
            if getattr(fx._REGISTRY.get(name), 'scope', 'sensor') == 'array':
                if where:
                    raise ValueError(f'{name} is one effect of the whole array: drop @{where}')
                if n_sensors < 3:
                    raise ValueError(f'{name} needs an array of at least three sensors')
                if name not in [e.name for e in array_effects]:
                    array_effects.append(fx.make_effect(name, 0))
                continue
            names = fx.BASE if name == 'base' else (name,)
            if where:
                try:
                    sensors = [int(where)]
                except ValueError:
                    raise ValueError(f'bad sensor in {tok!r}: expected name@<1..{n_sensors}>')
                if not 1 <= sensors[0] <= n_sensors:
                    raise ValueError(f'{tok!r}: sensor {sensors[0]} does not exist '
                                     f'(the data have sensors 1..{n_sensors})')
            else:
                sensors = range(1, n_sensors + 1)
            for nm in names:
                for j in sensors:
                    eff = fx.make_effect(nm, j)
                    if not eff.applies or eff.label in seen[j - 1] or any(
                            eff.label in o.supersedes for o in per_sensor[j - 1]):
                        continue
                    # a larger form of an effect already there replaces it (aux_poly > aux)
                    gone = [o for o in per_sensor[j - 1] if o.label in eff.supersedes]
                    for o in gone:
                        per_sensor[j - 1].remove(o)
                        seen[j - 1].discard(o.label)
                    clash = [o for o in per_sensor[j - 1]
                             if {o.name, o.label} & set(eff.excludes)
                             or {eff.name, eff.label} & set(o.excludes)]
                    if clash:
                        raise ValueError(
                            f'{eff.label} and {clash[0].label} on sensor {j} describe the same '
                            f'degrees of freedom ({eff.label}: {eff.describe()}; '
                            f'{clash[0].label}: {clash[0].describe()}); use one or the other')
                    seen[j - 1].add(eff.label)
                    per_sensor[j - 1].append(eff)
        for row in per_sensor:
            row.sort(key=lambda e: (e.kind != 'linear', e.linear_order))
        return cls(per_sensor, array_effects)

    def spec(self):
        """Canonical list of effect tokens (``name`` or ``name@j``)."""
        out = []
        labels = [[e.label for e in row] for row in self.effects]
        first = {}                            # label -> one instance
        for row in self.effects:
            for eff in row:
                first.setdefault(eff.label, eff)
        for lab, eff in first.items():
            have = [j + 1 for j, row in enumerate(labels) if lab in row]
            expected = list(range(1 if eff.on_sensor1 else 2, self.n_sensors + 1))
            if have == expected:
                out.append(lab)
            else:
                out.extend(f'{lab}@{j}' for j in have)
        return out + [e.label for e in self.array_effects]

    def with_effect(self, token):
        """A new model with ``token`` (e.g. 'temperature@2') added."""
        return Model.from_spec(self.spec() + [token], self.n_sensors)

    def has(self, j, name):
        """True if sensor j has an effect with this label or name."""
        return any(e.label == name or e.name == name for e in self.effects[j - 1])

    def frame_rotation(self, j):
        """True if sensor j has an effect holding its rotation into the array frame."""
        return any(e.frame_rotation for e in self.effects[j - 1])

    @property
    def joint(self):
        """True if sensors are tied to one field per epoch (an array-wide effect, or a frame
        rotation on j > 1: misalignment, soft iron)."""
        return self.n_sensors > 1 and (bool(self.array_effects) or any(
            self.frame_rotation(j) for j in range(2, self.n_sensors + 1)))

    def default_params(self):
        """(n_params,) parameters of ideal sensors."""
        p = np.zeros(self.n_params)
        for j, row in enumerate(self.effects):
            for eff, sl in zip(row, self.slices[j]):
                p[sl] = eff.default_params()
        for eff, sl in zip(self.array_effects, self.array_slices):
            p[sl] = eff.default_params()
        return p

    def param_info(self):
        """List of (sensor, effect label, name, unit) for each parameter."""
        out = []
        for j, row in enumerate(self.effects):
            for eff in row:
                for nm, un in zip(eff.param_names, eff.units):
                    out.append((j + 1, eff.label, nm, un))
        for eff in self.array_effects:          # sensor 0: the whole array
            out.extend((0, eff.label, nm, un) for nm, un in zip(eff.param_names, eff.units))
        return out

    def prepare(self, contexts):
        """Let effects compute their reference values (mean temperature, t0, ...)."""
        for row, ctx in zip(self.effects, contexts):
            for eff in row:
                eff.prepare(ctx)

    def check(self, contexts):
        """Reasons why effects cannot be excited by the data (empty list if all fine)."""
        out = []
        for row, ctx in zip(self.effects, contexts):
            for eff in row:
                why = eff.check(ctx)
                if why:
                    out.append(f'{eff.label}@{eff.sensor}: {why}')
        for eff in self.array_effects:
            why = eff.check(contexts[0]) if contexts else None
            if why:
                out.append(f'{eff.label}: {why}')
        return out

    # -- evaluation ------------------------------------------------------------------------

    def matrix(self, j, p):
        """(3, 3) linear map A_j of sensor j for the global parameter vector p."""
        a = np.eye(3)
        for eff, sl in zip(self.effects[j - 1], self.slices[j - 1]):
            if eff.kind == 'linear':
                a = a @ eff.matrix(p[sl])
        return a

    def additive(self, j, p, ctx, lin):
        """(N, 3) nT sum of the additive effects of sensor j."""
        out = np.zeros_like(lin)
        for eff, sl in zip(self.effects[j - 1], self.slices[j - 1]):
            if eff.kind != 'linear':
                out = out + eff.contribution(p[sl], ctx, lin)
        return out

    def array_shift(self, j, p, ctx):
        """(N, 3) nT field at sensor j minus the field at the array centre (array effects)."""
        out = 0.0
        for eff, sl in zip(self.array_effects, self.array_slices):
            out = out + eff.shift(p[sl], ctx, j)
        return out

    def forward(self, j, p, b, ctx):
        """Raw reading of sensor j (N, 3) nT for true field b (N, 3) nT in the array frame.

        ``b`` is the field at the array centre; array-wide effects (site gradient) shift it
        to the sensor's position before the sensor's linear map.
        """
        if self.array_effects:
            b = b + self.array_shift(j, p, ctx)
        lin = b @ self.matrix(j, p).T
        return lin + self.additive(j, p, ctx, lin)

    def correct(self, j, p, raw, ctx, n_iter=4, a_inv=None):
        """Invert :meth:`forward`: corrected field (N, 3) nT in the array frame.

        Additive effects that depend on the field itself (temperature scale, nonlinearity)
        are inverted by fixed-point iteration, which converges at rate |effect/field|.
        ``a_inv`` (3, 3) is A_j^-1 when the caller has it precomputed.
        """
        raw = np.asarray(raw, float)
        if a_inv is None:
            a_inv = np.linalg.inv(self.matrix(j, p))
        lin = raw - self.additive(j, p, ctx, raw)
        if any(e.depends_on_lin() for e in self.effects[j - 1]):
            for _ in range(n_iter):
                lin = raw - self.additive(j, p, ctx, lin)
        return lin @ a_inv.T

    def params_from_linear(self, j, a, o, p=None):
        """Set sensor j's linear and offset parameters from A (3, 3) and o (3,) nT.

        A is decomposed as A = U Q (RQ decomposition, U upper triangular with positive
        diagonal): U gives scale and nonorthogonality, Q the misalignment (paper 004 eq. 2-3);
        each effect takes its share (``Effect.params_from_linear``).  Effects the model lacks
        are dropped (their part of A is not representable).
        """
        p = self.default_params() if p is None else p.copy()
        parts = fx.decompose_linear(a, o)
        for eff, sl in zip(self.effects[j - 1], self.slices[j - 1]):
            share = eff.params_from_linear(parts)
            if share is not None:
                p[sl] = share
        return p


# -- fit ------------------------------------------------------------------------------------

@dataclass
class FitResult:
    """Outcome of :func:`fit` (attributes that end in _nt are in nT).

    Attributes
    ----------
    model : Model
    params : numpy.ndarray
        (P,) estimated parameters (units in ``model.param_info()``).
    stderr : numpy.ndarray
        (P,) standard uncertainties from the projected Jacobian.
    covariance, correlation : numpy.ndarray
        (P, P).
    sigma_nt : numpy.ndarray
        (S,) per-sensor noise standard deviation estimated from the residuals, nT.
    field_nt : numpy.ndarray
        (N, 3) estimated true field per epoch (array frame), nT.
    field_magnitude_nt : numpy.ndarray
        (N,) reference magnitude used, nT.
    corrected_nt : numpy.ndarray
        (S, N, 3) corrected readings in the array frame, nT.
    residual_nt : numpy.ndarray
        (S, N, 3) raw reading minus model prediction, nT.
    scalar_residual_nt : numpy.ndarray
        (S, N) |corrected| - reference magnitude, nT.
    vector_residual_nt : numpy.ndarray
        (S, N, 3) corrected_j - corrected_1, nT (zero for sensor 1).
    downweighted : numpy.ndarray
        (S,) number of sensor samples the robust loss down-weighted.
    """

    model: Model
    params: np.ndarray
    stderr: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    sigma_nt: np.ndarray
    field_nt: np.ndarray
    field_magnitude_nt: np.ndarray
    corrected_nt: np.ndarray
    residual_nt: np.ndarray
    scalar_residual_nt: np.ndarray
    vector_residual_nt: np.ndarray
    downweighted: np.ndarray
    success: bool
    status: int
    message: str
    nfev: int
    n_fit_samples: int
    chi2: float
    n_obs: int
    warnings: list = field(default_factory=list)
    identifiability: dict = field(default_factory=dict)
    initial_params: np.ndarray | None = None
    contexts: list | None = None
    robust: bool = False
    f_scale: float = 3.0

    @property
    def n_params(self):
        """Number of free parameters."""
        return self.model.n_params

    @property
    def scalar_rms_nt(self):
        """{sensor: RMS of the scalar residual} in nT."""
        return {j + 1: float(np.sqrt(np.mean(r ** 2)))
                for j, r in enumerate(self.scalar_residual_nt)}

    @property
    def vector_rms_nt(self):
        """{sensor j > 1: per-component RMS of corrected_j - corrected_1} in nT."""
        return {j + 1: float(np.sqrt(np.mean(self.vector_residual_nt[j] ** 2)))
                for j in range(1, self.model.n_sensors)}

    @property
    def calibration(self):
        """The :class:`Calibration` (model + parameters) for live correction."""
        cal = Calibration(self.model, self.params, self.stderr, self.sigma_nt)
        cols = self.model.array_cols
        if len(cols):
            cal.array_covariance = self.covariance[np.ix_(cols, cols)].copy()
            cal.site_frame = self.identifiability.get('site_gradient_frame', cal.site_frame)
        return cal

    def param_table(self):
        """List of dicts: sensor, effect, name, unit, value, stderr."""
        return [dict(sensor=s, effect=e, name=n, unit=u, value=float(v), stderr=float(se))
                for (s, e, n, u), v, se in zip(self.model.param_info(), self.params,
                                               self.stderr)]

    def summary(self):
        """Short text report."""
        lines = [f'model: {",".join(self.model.spec())}  ({self.n_params} parameters, '
                 f'{self.n_fit_samples} epochs fitted)',
                 f'converged: {self.success} ({self.message})']
        for j, r in self.scalar_rms_nt.items():
            v = self.vector_rms_nt.get(j)
            lines.append(f'  sensor {j}: scalar RMS {r:8.2f} nT, sigma {self.sigma_nt[j-1]:.2f} nT'
                         + (f', vector RMS vs sensor 1 {v:8.2f} nT' if v is not None else ''))
        for i, w in enumerate(self.warnings, 1):
            lines.append(f'[{i}] {w}')
        return '\n'.join(lines)


class Calibration:
    """A fitted model for live correction.

    Parameters
    ----------
    model : Model
    params : numpy.ndarray
        (P,) parameter vector.
    stderr : numpy.ndarray, optional
        (P,) standard uncertainties.
    sigma_nt : numpy.ndarray, optional
        (S,) per-sensor noise in nT.
    """

    def __init__(self, model, params, stderr=None, sigma_nt=None):
        self.model = model
        self.params = np.asarray(params, float)
        self.stderr = np.zeros_like(self.params) if stderr is None else np.asarray(stderr)
        self.sigma_nt = (np.full(model.n_sensors, np.nan) if sigma_nt is None
                         else np.asarray(sigma_nt, float))
        #: (K, K) covariance of the array-wide parameters (site gradient), when known
        self.array_covariance = None
        #: frame of the site gradient: the attitude's world frame, or the field-aligned
        #: frame of a fit without attitude (core.site_gradient.FIELD_ALIGNED)
        self.site_frame = 'world'
        # A calibration is immutable: precompute what every correction needs
        self._a_inv = [np.linalg.inv(model.matrix(j, self.params))
                       for j in range(1, model.n_sensors + 1)]

    @property
    def n_sensors(self):
        """Number of sensors."""
        return self.model.n_sensors

    def matrix(self, j):
        """(3, 3) forward linear map A_j of sensor j."""
        return self.model.matrix(j, self.params)

    def correction_matrix(self, j):
        """(3, 3) A_j^-1: corrected = A_j^-1 (raw - offset - driven)."""
        return self._a_inv[j - 1].copy()

    def offset(self, j):
        """(3,) nT constant offset of sensor j: the sum of its constant additive effects
        (``Effect.constant``, the offset); zero if the model has none."""
        out = np.zeros(3)
        ctx = fx.SensorContext(t=np.zeros(1))
        for eff, sl in zip(self.model.effects[j - 1], self.model.slices[j - 1]):
            if eff.kind != 'linear' and eff.constant:
                out = out + eff.contribution(self.params[sl], ctx, np.zeros((1, 3)))[0]
        return out

    def intrinsic_and_rotation(self, j):
        """(C^-1 (3, 3) upper triangular, R (3, 3)) with A_j^-1 = R C^-1 (paper 004 eq. 5, 14).

        R takes sensor j's corrected field into sensor 1's frame (identity for sensor 1).
        """
        u, q = fx.rq_positive(self.matrix(j))
        return np.linalg.inv(u), q.T

    def site_gradient(self):
        """(G_w (3, 3), stderr (3, 3)) nT/m, world frame, or None without the effect.

        The standard uncertainty of gzz = -gxx - gyy needs the covariance of the fit
        (``array_covariance``); without it that entry is nan.
        """
        from magcal_ros.core.site_gradient import gradient_from_fit
        cov = np.diag(self.stderr ** 2)
        cols = self.model.array_cols
        if self.array_covariance is not None:
            cov[np.ix_(cols, cols)] = self.array_covariance
        out = gradient_from_fit(self.model, self.params, cov)
        if out is None:
            return None
        se = out[1]
        if self.array_covariance is None:
            se[2, 2] = np.nan
        return out[0], se

    def array_shift(self, j, ctx):
        """(N, 3) nT modelled field at sensor j minus the centre field (site gradient).

        ``ctx.attitude`` (N, 3, 3) is needed; zero without array-wide effects.
        """
        if not self.model.array_effects:
            return np.zeros((len(ctx.t), 3))
        return self.model.array_shift(j, self.params, ctx)

    def driven_effects(self, j):
        """Labels of the additive effects of sensor j that are not constant (they are
        evaluated per sample, from the signals they declare: temperature, aux, ...)."""
        return [e.label for e in self.model.effects[j - 1]
                if e.kind != 'linear' and not e.constant]

    def signals(self, j):
        """Driving signals the effects of sensor j read (``Effect.signals``), in order."""
        out = []
        for eff in self.model.effects[j - 1]:
            out.extend(s for s in eff.signals if s not in out)
        return out

    def correct(self, j, raw, ctx=None):
        """Corrected field of sensor j in the array frame.

        Parameters
        ----------
        j : int
            Sensor, 1-based.
        raw : numpy.ndarray
            (N, 3) or (3,) raw reading in nT.
        ctx : SensorContext, optional
            Driving signals; required when the model has driven effects.
        """
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


def _tangent_basis(u):
    """Two unit vectors (N, 3) each, orthogonal to the unit vectors u (N, 3) and to each other."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return e1, e2


def _solve2x2(m, rhs):
    """Solve the stacked 2x2 systems m (N, 2, 2) x = rhs (N, 2, K) in closed form.

    Same result as ``np.linalg.solve`` (to rounding) for the well-conditioned tangent-plane
    Gram matrices here, about 50x faster for K = 40 right-hand sides (bench/ profile: the
    batched LAPACK call dominated the projection of the Jacobian).
    """
    i = _inv2x2(m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1])
    inv = np.stack([np.stack(i[:2], axis=1), np.stack(i[2:], axis=1)], axis=1)
    return inv @ rhs


def _inv2x2(a, b, c, d):
    """Entries (each (N,)) of the inverses of the stacked 2x2 matrices [[a, b], [c, d]]."""
    det = a * d - b * c
    return d / det, -b / det, -c / det, a / det


class _Problem:
    """Residuals and projected Jacobian of the ML problem for one group of sensors."""

    def __init__(self, model, data_raw, contexts, f_nt, sensors, sigma, priors, robust=False,
                 f_scale=3.0):
        self.robust = robust
        self.f_scale = f_scale
        self.model = model
        self.raw = data_raw            # (S, N, 3)
        self.ctx = contexts
        self.f = f_nt                  # (N,)
        self.sensors = sensors         # 1-based sensor numbers of this group
        self.sigma = sigma             # (S,) nT
        self.cols = np.concatenate([np.arange(model.n_params)[model.sensor_slices[j - 1]]
                                    for j in sensors] + [model.array_cols]).astype(int)
        self.priors = priors           # list of (index, mean, sd) with index into full p
        self._cache_key = None
        self.p_full = model.default_params()
        self.field0 = None             # (N, 3) nT warm start of the field profile, optional

    def full(self, x):
        p = self.p_full.copy()
        p[self.cols] = x
        return p

    def _field(self, p):
        """Profile the field per epoch: mean of corrected readings, then GN steps on |B| = F.

        With :attr:`field0` (N, 3) nT set (the profiled field of nearby parameters), start
        from it and take one step: Gauss-Newton converges quadratically, so one step from a
        field 1e-4 rad off lands within 1e-8 rad of two steps from the mean.
        """
        n = self.raw.shape[1]
        mats = {j: self.model.matrix(j, p) for j in self.sensors}
        if self.field0 is not None:
            b, steps = self.field0, 1
        else:
            cor = np.stack([self.model.correct(j, p, self.raw[j - 1], self.ctx[j - 1])
                            for j in self.sensors])
            if self.robust and len(self.sensors) > 2:
                acc = np.median(cor, axis=0)      # one spiking sensor cannot pull the field
            else:
                acc = np.einsum('gnc,g->nc', cor,
                                1.0 / self.sigma[np.array(self.sensors) - 1] ** 2)
            u = acc / np.linalg.norm(acc, axis=1, keepdims=True)
            b, steps = u * self.f[:, None], 2
        for _ in range(steps):
            u = b / self.f[:, None]
            e1, e2 = _tangent_basis(u)
            # per-epoch 2 x 2 normal equations of the two tangent directions, written out
            # component by component: several times faster than stacking (N, 3, 2) arrays
            # and batched matmuls of tiny matrices (profile of diagnose, bench/)
            h11, h12, h22 = np.zeros(n), np.zeros(n), np.zeros(n)
            g1s, g2s = np.zeros(n), np.zeros(n)
            for j in self.sensors:
                r = (self.raw[j - 1] - self.model.forward(j, p, b, self.ctx[j - 1])) / (
                    self.sigma[j - 1])
                scale = self.f[:, None] / self.sigma[j - 1]
                g1 = (e1 @ mats[j].T) * scale          # (N, 3) = -dr/d delta_1
                g2 = (e2 @ mats[j].T) * scale          # (N, 3) = -dr/d delta_2
                if self.robust:
                    # IRLS weight of the soft-L1 loss on this sensor's residual at each epoch
                    w = 1.0 / np.sqrt(1.0 + np.sum(r * r, axis=1) / self.f_scale ** 2)
                    wg1, wg2 = g1 * w[:, None], g2 * w[:, None]
                else:
                    wg1, wg2 = g1, g2
                h11 += np.einsum('ij,ij->i', wg1, g1)
                h12 += np.einsum('ij,ij->i', wg1, g2)
                h22 += np.einsum('ij,ij->i', wg2, g2)
                g1s += np.einsum('ij,ij->i', wg1, r)
                g2s += np.einsum('ij,ij->i', wg2, r)
            i11, i12, i21, i22 = _inv2x2(h11, h12, h12, h22)
            d1 = i11 * g1s + i12 * g2s
            d2 = i21 * g1s + i22 * g2s
            b = b + self.f[:, None] * (d1[:, None] * e1 + d2[:, None] * e2)
            b = b / np.linalg.norm(b, axis=1, keepdims=True) * self.f[:, None]
        return b, mats

    def evaluate(self, x):
        key = x.tobytes()
        if key != self._cache_key:
            p = self.full(x)
            b, mats = self._field(p)
            res = np.stack([(self.raw[j - 1] - self.model.forward(j, p, b, self.ctx[j - 1]))
                            / self.sigma[j - 1] for j in self.sensors], axis=1)   # (N, G, 3)
            self._cache = (p, b, mats, res)
            self._cache_key = key
        return self._cache

    def residuals(self, x):
        p, _, _, res = self.evaluate(x)
        out = res.ravel()
        if self.priors:
            pr = np.array([(p[i] - m) / s for i, m, s in self.priors])
            out = np.concatenate([out, pr])
        return out

    def jacobian(self, x):
        p, b, mats, res = self.evaluate(x)
        n, g = res.shape[0], len(self.sensors)
        jac = np.zeros((n, g, 3, len(self.cols)))
        col = 0
        for gi, j in enumerate(self.sensors):
            sl = self.model.sensor_slices[j - 1]
            base = self.model.forward(j, p, b, self.ctx[j - 1])
            # this sensor's columns, filled contiguously (P_j, N, 3) and copied into the
            # strided Jacobian once: about 2x faster than writing column by column
            block = np.empty((sl.stop - sl.start, n, 3))
            for c, i in enumerate(range(sl.start, sl.stop)):
                h = 1e-6 * max(1.0, abs(p[i]))
                pp = p.copy()
                pp[i] += h
                np.subtract(base, self.model.forward(j, pp, b, self.ctx[j - 1]), out=block[c])
                block[c] /= h * self.sigma[j - 1]
            jac[:, gi, :, col:col + len(block)] = block.transpose(1, 2, 0)
            col += len(block)
        # array-wide parameters (site gradient): every sensor of the group depends on them
        n_arr = len(self.model.array_cols)
        bases = ([self.model.forward(j, p, b, self.ctx[j - 1]) for j in self.sensors]
                 if n_arr else [])
        for k, i in enumerate(self.model.array_cols):
            h = 1e-6 * max(1.0, abs(p[i]))
            pp = p.copy()
            pp[i] += h
            for gi, j in enumerate(self.sensors):
                d = bases[gi] - self.model.forward(j, pp, b, self.ctx[j - 1])
                jac[:, gi, :, len(self.cols) - n_arr + k] = d / (h * self.sigma[j - 1])
        # project out the nuisance field directions (variable projection)
        u = b / self.f[:, None]
        e1, e2 = _tangent_basis(u)
        gb = np.concatenate([np.stack([e1 @ mats[j].T, e2 @ mats[j].T], axis=2)
                             * (self.f[:, None, None] / self.sigma[j - 1])
                             for j in self.sensors], axis=1)           # (N, 3G, 2)
        jac = jac.reshape(n, 3 * g, -1)
        gbt = np.swapaxes(gb, 1, 2)                    # batched matmul, not einsum: 3-5x faster
        jac = jac - gb @ _solve2x2(gbt @ gb, gbt @ jac)
        jac = jac.reshape(n * 3 * g, -1)
        if self.priors:
            pr = np.zeros((len(self.priors), len(self.cols)))
            where = {c: k for k, c in enumerate(self.cols)}
            for r, (i, _, s) in enumerate(self.priors):
                pr[r, where[i]] = 1.0 / s
            jac = np.vstack([jac, pr])
        return jac


def _priors_for(model, spec, constrained=False):
    """Prior list [(index, mean, sd)] from a {effect name or label: (mean, sd)} spec.

    With ``constrained`` every effect that declares an ``Effect.prior`` gets it, unless
    ``spec`` overrides it; a mean of None is the effect's default parameter value.
    """
    out = []
    default = model.default_params()
    for j, row in enumerate(model.effects):
        for eff, sl in zip(row, model.slices[j]):
            prior = spec.get(eff.label, spec.get(eff.name,
                                                 eff.prior if constrained else None))
            if prior is not None:
                mean, sd = prior
                for i in range(sl.start, sl.stop):
                    out.append((i, default[i] if mean is None else mean, sd))
    return out


def initial_params(raw, field_nt, model, constrained=False):
    """Closed-form starting values (paper 004 section 3).

    Per sensor: ellipsoid fit + Cholesky (eq. 8-13); Procrustes rotation of each corrected
    sensor onto sensor 1 (eq. 14); A_j = C_j R_j^T.  In constrained mode (partial attitude
    coverage, where the ellipsoid is ill-determined) A = I and only the offset is solved,
    from the linear sphere fit |m - o|^2 = F^2.

    Parameters
    ----------
    raw : numpy.ndarray
        (S, N, 3) raw readings, nT.
    field_nt : numpy.ndarray
        (N,) reference magnitude, nT.
    """
    s = raw.shape[0]
    f0 = float(np.mean(field_nt))
    p = model.default_params()
    corrected = []
    mats = []
    for j in range(1, s + 1):
        m = raw[j - 1]
        if constrained:
            # |m|^2 = 2 m.o + (F^2 - |o|^2): linear in (o, c)
            design = np.column_stack([2 * m, np.ones(len(m))])
            sol, *_ = np.linalg.lstsq(design, (m ** 2).sum(1) - field_nt ** 2 + f0 ** 2,
                                      rcond=None)
            c_inv, o = np.eye(3), sol[:3]
        else:
            ell = fit_ellipsoid(m, f0)
            c_inv, o = ell.c_inv, ell.b
        corrected.append((m - o) @ c_inv.T)
        mats.append((c_inv, o))
    for j in range(1, s + 1):
        c_inv, o = mats[j - 1]
        rot = np.eye(3)
        if j > 1 and model.frame_rotation(j):
            rot = procrustes_rotation(corrected[0], corrected[j - 1])       # eq. 14
        a = np.linalg.inv(c_inv) @ rot.T
        p = model.params_from_linear(j, a, o, p)
    return p


@dataclass
class _Solution:
    x: np.ndarray
    success: bool
    status: int
    message: str
    nfev: int


def _levenberg_marquardt(fun, jac, x0, robust=False, f_scale=3.0, max_nfev=200, xtol=1e-10,
                         ftol=1e-12):
    """Minimise sum rho(r_i^2) by Levenberg-Marquardt on the normal equations.

    rho is the identity or the soft-L1 loss 2 f^2 (sqrt(1 + r^2/f^2) - 1) (handled by
    iteratively reweighted least squares).  Marquardt's diagonal scaling makes the damping
    invariant to parameter units.  Returns an object with the fields of scipy's
    OptimizeResult that :func:`fit` uses (x, success, status, message, nfev).
    """
    def cost(r):
        if robust:
            return float(np.sum(f_scale ** 2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))
        return 0.5 * float(r @ r)

    x = np.asarray(x0, float).copy()
    r = fun(x)
    c = cost(r)
    nfev = 1
    lam = 1e-3
    for _ in range(max_nfev):
        j = jac(x)
        if robust:
            w = np.sqrt(1.0 / np.sqrt(1 + (r / f_scale) ** 2))
            j, rw = j * w[:, None], r * w
        else:
            rw = r
        a = j.T @ j
        g = j.T @ rw
        d = np.diag(a).copy()
        d[d <= 0] = 1.0
        while True:
            try:
                step = -np.linalg.solve(a + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step
            r_new = fun(x_new)
            nfev += 1
            c_new = cost(r_new)
            if c_new <= c:
                break
            lam *= 10
            if lam > 1e12:
                return _Solution(x, True, 2, 'no further decrease of the cost', nfev)
            if nfev >= max_nfev:
                # out of evaluations while still looking for a downhill step: not converged
                return _Solution(x, False, 0, f'maximum number of evaluations ({max_nfev}) '
                                 'reached', nfev)
        dc = c - c_new
        x, r, c = x_new, r_new, c_new
        lam = max(lam / 10, 1e-12)
        scaled = np.sqrt(d)
        if np.linalg.norm(scaled * step) <= xtol * (np.linalg.norm(scaled * x) + xtol):
            return _Solution(x, True, 3, 'step below xtol', nfev)
        if dc <= ftol * max(c, 1e-300):
            return _Solution(x, True, 2, 'cost decrease below ftol', nfev)
        if nfev >= max_nfev:
            break
    return _Solution(x, False, 0, f'maximum number of evaluations ({max_nfev}) reached', nfev)


def _covariance(jac):
    """(P, P) inverse of J^T J with column scaling; inf variance for undetermined directions.

    A pseudo-inverse would silently give *zero* variance along directions the data do not
    determine; here such parameters get an infinite standard uncertainty instead.
    """
    d = np.linalg.norm(jac, axis=0)
    d[d == 0] = 1.0
    m = (jac / d).T @ (jac / d)
    w, v = np.linalg.eigh(m)
    bad = w <= 1e-14 * max(w.max(), 1e-300)
    w_inv = np.where(bad, 0.0, 1.0 / np.where(bad, 1.0, w))
    cov = (v * w_inv) @ v.T / np.outer(d, d)
    if bad.any():
        involved = np.abs(v[:, bad]).max(axis=1) > 1e-6
        cov[involved, :] = np.inf
        cov[:, involved] = np.inf
        cov[involved, involved] = np.inf
    return cov


def _single_threaded_blas():
    """Limit BLAS to one thread inside a fit (optional threadpoolctl).

    The fit's linear algebra is tall-skinny products and P x P solves; on small machines
    shared with other processes (a robot's computer, CI), BLAS threads only contend:
    measured 2-6x slower with two threads on a loaded 2-core machine (bench/).
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:                   # pragma: no cover - optional dependency
        import contextlib
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api='blas')


def fit(data, model, field_nt=None, **kwargs):
    with _single_threaded_blas():
        return _fit(data, model, field_nt, **kwargs)


def _fit(data, model, field_nt=None, *, robust=False, f_scale=3.0, constrained=False,
         priors=None, sigma_nt=None, on_degenerate='raise', max_fit_samples=20000,
         init=None, max_nfev=200, check_identifiability=True, solver='lm'):
    """Maximum-likelihood fit of ``model`` to rotation data in a uniform field.

    Parameters
    ----------
    data : Dataset
        (S sensors, N epochs) raw readings in nT.
    model : Model or str
        Model or spec string ('base', 'base,temperature@2', ...).
    field_nt : float or numpy.ndarray, optional
        Reference magnitude in nT, scalar or (N,); default ``data.ref_total``.
    robust : bool
        Use the soft-L1 loss (outlier spikes); ``f_scale`` is in units of sigma.
    constrained : bool
        Constrained mode for partial attitude coverage: effects get the priors they declare
        (``Effect.prior``: scale 1 +- 0.02, non-orthogonality 0 +- 0.02 rad, misalignment
        0 +- 0.05 rad, soft iron identity +- 0.02) and the start is A = I.
    priors : dict, optional
        {effect name or label: (mean or None for default, sd)} overriding the priors.
    sigma_nt : float or numpy.ndarray, optional
        Fixed per-sensor noise (nT); default: estimated from the residuals.
    on_degenerate : {'raise', 'flag'}
        Refuse (DegenerateDataError) or flag (warnings) data that cannot determine the model.
    max_fit_samples : int or None
        Fit on at most this many epochs, evenly spaced; residuals are reported for all.
    init : numpy.ndarray, optional
        (P,) starting parameters (default: closed-form start).
    solver : {'lm', 'scipy'}
        'lm': Levenberg-Marquardt on the normal equations (J^T J is P x P; about 20x faster
        than an SVD of the tall Jacobian, see bench/); 'scipy': scipy.optimize.least_squares
        (trust-region reflective), the reference implementation.  Both minimise the same
        cost (test_model_ml.py checks they agree).

    Returns
    -------
    FitResult
    """
    from magcal_ros.core import identifiability as idf

    if isinstance(model, str):
        model = Model.from_spec(model, data.n_sensors)
    if model.n_sensors != data.n_sensors:
        raise ValueError(f'model has {model.n_sensors} sensors, data have {data.n_sensors}')
    if on_degenerate not in ('raise', 'flag'):
        raise ValueError("on_degenerate must be 'raise' or 'flag'")
    f_all = reference_magnitude(data, field_nt)
    raw_all = data.raw
    if not np.all(np.isfinite(raw_all)):
        bad = np.unique(np.nonzero(~np.isfinite(raw_all))[0]) + 1
        raise ValueError(f'non-finite raw readings for sensor(s) {bad.tolist()}: drop those rows')
    contexts_all = [data.context(j) for j in range(1, data.n_sensors + 1)]
    model.prepare(contexts_all)
    notes = []

    def degenerate(msg):
        if on_degenerate == 'raise':
            raise DegenerateDataError(msg)
        notes.append(Note(msg, 'degenerate'))

    for why in model.check(contexts_all):
        degenerate(why)
    n_min = max(12, int(np.ceil(2 * model.n_params / max(1, data.n_sensors))))
    if data.n_samples < n_min:
        raise DegenerateDataError(f'too few samples: {data.n_samples} epochs for '
                                  f'{model.n_params} parameters; collect at least {n_min}')

    ident = {}
    if check_identifiability:
        ident = idf.check_coverage(raw_all)
        problems = ident['problems']
        if constrained:
            # the priors stand in for the attitudes a partial or single-axis coverage never
            # saw; they cannot make up for a sensor that did not turn or is stuck
            excused = [j for j, v in ident['sensors'].items()
                       if v['status'] in ('partial', 'single axis')]
            problems = [p for p in problems
                        if not any(p.startswith(f'sensor {j}:') for j in excused)]
        if problems:
            degenerate(problems[0])

    # subsample for the fit
    idx = np.arange(data.n_samples)
    if max_fit_samples and data.n_samples > max_fit_samples:
        idx = np.unique(np.linspace(0, data.n_samples - 1, max_fit_samples).round().astype(int))
    raw = raw_all[:, idx]
    f = f_all[idx]
    contexts = [c.subset(idx) for c in contexts_all]

    if init is None:
        try:
            p0 = initial_params(raw, f, model, constrained=constrained)
        except ValueError as exc:
            if constrained:
                raise
            degenerate(f'{exc}. {ident.get("summary", "")}'.strip())
            # flagged: start from ideal sensors and the sphere-fit offsets instead
            p0 = initial_params(raw, f, model, constrained=True)
    else:
        p0 = np.asarray(init, float).copy()
    if model.array_effects and contexts_all[0].attitude is not None:
        # the attitude must agree with the field direction (closed-form corrected sensor 1)
        from magcal_ros.core.attitude import check_against_field
        check_against_field(contexts_all[0].attitude,
                            model.correct(1, p0, raw_all[0], contexts_all[0]), data.t)

    prior_list = _priors_for(model, priors or {}, constrained)

    groups = ([list(range(1, model.n_sensors + 1))] if model.joint
              else [[j] for j in range(1, model.n_sensors + 1)])
    sigma = (np.ones(model.n_sensors) * 3.0 if sigma_nt is None
             else np.broadcast_to(np.asarray(sigma_nt, float), (model.n_sensors,)).copy())
    fixed_sigma = sigma_nt is not None
    p = p0.copy()
    status, message, nfev, success = 0, '', 0, True
    for it in range(3 if not fixed_sigma else 1):
        if not fixed_sigma and it == 0:
            # start from a robust noise estimate of the closed-form residuals
            for j in range(1, model.n_sensors + 1):
                corr = model.correct(j, p, raw[j - 1], contexts[j - 1])
                sigma[j - 1] = max(mad_sd(np.linalg.norm(corr, axis=1) - f), 1e-3)
        status, message, nfev, success = 0, '', 0, True
        problems = []
        for grp in groups:
            pr = [t for t in prior_list if any(
                model.sensor_slices[j - 1].start <= t[0] < model.sensor_slices[j - 1].stop
                for j in grp)]
            prob = _Problem(model, raw, contexts, f, grp, sigma, pr, robust, f_scale)
            prob.p_full = p.copy()
            x0 = p[prob.cols]
            if solver == 'scipy':
                sol = least_squares(prob.residuals, x0, jac=prob.jacobian, x_scale='jac',
                                    loss='soft_l1' if robust else 'linear', f_scale=f_scale,
                                    max_nfev=max_nfev, method='trf')
            else:
                sol = _levenberg_marquardt(prob.residuals, prob.jacobian, x0, robust=robust,
                                           f_scale=f_scale, max_nfev=max_nfev)
            p[prob.cols] = sol.x
            problems.append(prob)
            nfev += sol.nfev
            success &= bool(sol.success)
            status = sol.status
            message = sol.message
        if fixed_sigma:
            break
        # re-estimate the noise per sensor from the raw residuals
        new_sigma = sigma.copy()
        for prob in problems:
            _, _, _, res = prob.evaluate(p[prob.cols])
            g = len(prob.sensors)
            dof_per = max(1.0, (3 * g - 2) / g * res.shape[0] - len(prob.cols) / g)
            for gi, j in enumerate(prob.sensors):
                r = res[:, gi] * sigma[j - 1]
                if robust:
                    new_sigma[j - 1] = mad_sd(r) * np.sqrt((3 * g - 2) / (3 * g))
                else:
                    new_sigma[j - 1] = np.sqrt(np.sum(r ** 2) / dof_per)
        converged = np.all(np.abs(new_sigma / sigma - 1) < 0.05)
        sigma = np.maximum(new_sigma, 1e-6)
        if converged:
            break

    # covariance from the projected Jacobian at the solution
    n_p = model.n_params
    cov = np.zeros((n_p, n_p))
    chi2 = 0.0
    n_obs = 0
    for grp in groups:
        prob = _Problem(model, raw, contexts, f, grp, sigma, [t for t in prior_list if any(
            model.sensor_slices[j - 1].start <= t[0] < model.sensor_slices[j - 1].stop
            for j in grp)], robust, f_scale)
        prob.p_full = p.copy()
        x = p[prob.cols]
        jac = prob.jacobian(x)
        r = prob.residuals(x)
        chi2 += float(np.sum(r ** 2))
        n_obs += (3 * len(grp) - 2) * raw.shape[1]
        cov[np.ix_(prob.cols, prob.cols)] = _covariance(jac)
    stderr = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid='ignore', divide='ignore'):
        corr = cov / np.outer(stderr, stderr)
    corr[~np.isfinite(corr)] = 0.0
    np.fill_diagonal(corr, 1.0)

    if check_identifiability:
        jac_rep = idf.jacobian_report(model, cov, corr, constrained=constrained)
        ident.update(jac_rep)
        for prob_msg in jac_rep['problems']:
            degenerate(prob_msg)

    if not success:
        notes.append(Note(f'the optimiser did not converge: {message}', 'not_converged'))

    # residuals on all samples
    out = evaluate(model, p, data, f_all, sigma, contexts_all, robust=robust, f_scale=f_scale)
    return FitResult(
        model=model, params=p, stderr=stderr, covariance=cov, correlation=corr,
        sigma_nt=sigma, field_nt=out['field'], field_magnitude_nt=f_all,
        corrected_nt=out['corrected'], residual_nt=out['residual'],
        scalar_residual_nt=out['scalar'], vector_residual_nt=out['vector'],
        downweighted=out['downweighted'], success=success, status=status, message=message,
        nfev=nfev, n_fit_samples=len(idx), chi2=chi2, n_obs=n_obs, warnings=notes,
        identifiability=ident, initial_params=p0, contexts=contexts_all,
        robust=bool(robust), f_scale=float(f_scale))


fit.__doc__ = _fit.__doc__


def evaluate(model, p, data, f, sigma, contexts=None, robust=False, f_scale=3.0,
             chunk=200000, field0=None):
    """Residuals of parameters ``p`` on all epochs of ``data`` (chunked for large N).

    ``field0`` (N, 3) nT, optional: the profiled field of nearby parameters (e.g. the
    ``field`` of an evaluation of the fit), to start the field profile from (joint models).

    Returns a dict of arrays: field (N, 3), corrected (S, N, 3), residual (S, N, 3),
    scalar (S, N), vector (S, N, 3), all in nT, and downweighted (S,) counts.
    """
    if contexts is None:
        contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    s, n = data.n_sensors, data.n_samples
    groups = ([list(range(1, s + 1))] if model.joint else [[j] for j in range(1, s + 1)])
    field = np.zeros((n, 3))
    residual = np.zeros((s, n, 3))
    for start in range(0, n, chunk):
        sl = slice(start, min(n, start + chunk))
        if sl.start == 0 and sl.stop == n:
            ctx = contexts                      # one chunk: no copies of the signals
        else:
            idx = np.arange(sl.start, sl.stop)
            ctx = [c.subset(idx) for c in contexts]
        for grp in groups:
            prob = _Problem(model, data.raw[:, sl], ctx, f[sl], grp, sigma, [], robust, f_scale)
            prob.p_full = p.copy()
            if field0 is not None and model.joint:
                prob.field0 = field0[sl]
            _, b, _, res = prob.evaluate(p[prob.cols])
            field[sl] = b          # joint: shared; independent: last sensor's estimate
            for gi, j in enumerate(grp):
                residual[j - 1, sl] = res[:, gi] * sigma[j - 1]
    corrected = np.stack([model.correct(j, p, data.raw[j - 1], contexts[j - 1])
                          for j in range(1, s + 1)])
    centred = corrected
    if model.array_effects:
        # residuals against the centre field: remove each sensor's modelled site shift
        centred = corrected - np.stack([model.array_shift(j, p, contexts[j - 1])
                                        for j in range(1, s + 1)])
    scalar = np.linalg.norm(centred, axis=2) - f[None]
    vector = centred - centred[:1]
    down = np.zeros(s, int)
    if robust:
        down = (np.abs(residual / sigma[:, None, None]) > f_scale).any(axis=2).sum(axis=1)
    return dict(field=field, corrected=corrected, residual=residual, scalar=scalar,
                vector=vector, downweighted=down)


def data_hash(data):
    """SHA-256 of the raw readings and times (provenance)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data.t).tobytes())
    h.update(np.ascontiguousarray(data.raw).tobytes())
    return h.hexdigest()
