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
Composable calibration models of a magnetometer array: :class:`Model`.

A list of effects per sensor (:mod:`magcal_ros.core.effects`) with a flat parameter vector,
built from a formula (docs/design.md §2); it predicts each raw reading from the true field
(:meth:`Model.forward`) and inverts that (:meth:`Model.correct`).
"""
import hashlib

from magcal_ros.core import effects as fx
import numpy as np

__all__ = ['data_hash', 'Model']


class Model:
    """
    Effects per sensor, with a flat parameter vector.

    ``effects[j-1]`` sensor j's; ``array_effects`` one parameter set for the whole array,
    after the sensors'; ``drops`` (t0, t1) s or (t0, t1, sensors 1-based or None).
    """

    def __init__(self, effects, array_effects=(), drops=()):
        self.effects = [list(e) for e in effects]
        self.array_effects = list(array_effects)
        self.drops = []
        for w in drops:
            who = tuple(int(j) for j in w[2]) if len(w) > 2 and w[2] is not None else None
            bad = [j for j in who or () if not 1 <= j <= self.n_sensors]
            if bad:
                raise ValueError(f'drop({w[0]:g}, {w[1]:g})@{bad[0]}: sensor {bad[0]} does '
                                 f'not exist (the data have sensors 1..{self.n_sensors})')
            self.drops.append((float(w[0]), float(w[1]), who))
        if self.array_effects and self.n_sensors == 4:
            from magcal_ros.core.geometry.tensor import cross_positions
            for eff in self.array_effects:
                if hasattr(eff, 'set_positions') and 'x1' not in eff.refs:
                    eff.set_positions(cross_positions(0.5))     # paper 004's cross
        self._layout()

    def _layout(self):
        """Lay the parameters out: each sensor's own, the array effects', the shared (@alike)."""
        end = [0]

        def take(n):
            end[0] += n
            return slice(end[0] - n, end[0])
        self.slices, self.sensor_slices = [], []
        for row in self.effects:
            start = end[0]
            self.slices.append([None if getattr(e, 'shared', False) else take(e.n_params)
                                for e in row])
            self.sensor_slices.append(slice(start, end[0]))
        self.array_slices = [take(e.n_params) for e in self.array_effects]
        shared = {}
        for e in (e for row in self.effects for e in row if getattr(e, 'shared', False)):
            shared.setdefault(e.label, e.n_params)
        #: {label: slice} of the parameters shared by every sensor (scope alike)
        self.shared_slices = {lab: take(n) for lab, n in shared.items()}
        self.slices = [[self.shared_slices[e.label] if sl is None else sl
                        for e, sl in zip(row, sls)] for row, sls in zip(self.effects, self.slices)]
        self.n_params = end[0]

    def effect_slices(self):
        """[(sensor, effect, slice)] of every effect: each sensor's (1-based), the array's (0)."""
        return [(j, e, sl) for j, (row, sls) in enumerate(zip(self.effects, self.slices), 1)
                for e, sl in zip(row, sls)] + [
                    (0, e, sl) for e, sl in zip(self.array_effects, self.array_slices)]

    @property
    def array_cols(self):
        """(K,) indices of the parameters of the whole array (array effects, shared sets)."""
        sls = self.array_slices + list(self.shared_slices.values())
        return np.concatenate([np.arange(sl.start, sl.stop) for sl in sls]
                              ).astype(int) if sls else np.zeros(0, int)

    def set_positions(self, positions):
        """Sensor positions (S, 3) m in the array frame, for the array-wide effects."""
        for eff in self.array_effects:
            if hasattr(eff, 'set_positions'):
                eff.set_positions(positions)

    @property
    def n_sensors(self):
        """Return the number of sensors S."""
        return len(self.effects)

    @classmethod
    def from_spec(cls, spec, n_sensors):
        """Build a model from formula text, terms or a Formula (docs/formulas.md), S sensors."""
        from magcal_ros.core.effects.formula import composed_effect, parse
        formula = parse(spec)
        per_sensor = [[] for _ in range(n_sensors)]
        array_effects = []
        for term in formula.terms:
            if term.kind == 'drop':
                if term.dropped:
                    term.sensors(n_sensors)         # refuses a sensor the data do not have
                continue
            if term.kind == 'composed':
                eff0 = composed_effect(term, 0)
                if eff0.scope == 'array':
                    if eff0.label not in [e.label for e in array_effects]:
                        array_effects.append(eff0)
                    continue
                if term.scope == 'alike' and n_sensors < 2:
                    raise ValueError(f'{term.text}: @alike shares parameters between sensors; '
                                     'the data have one sensor (drop @alike)')
                makers = [lambda j, t=term: composed_effect(t, j)]
            elif term.scope == 'array':
                eff = fx.make_effect(term.core, 0)
                if n_sensors < 3 and hasattr(eff, 'set_positions'):
                    raise ValueError(f'{term.core} needs an array of at least three sensors')
                if term.core not in [e.name for e in array_effects]:
                    array_effects.append(eff)
                continue
            else:
                names = fx.BASE if term.core == 'base' else (term.core,)
                makers = [lambda j, nm=nm: fx.make_effect(nm, j) for nm in names]
            sensors = term.sensors(n_sensors)
            for make in makers:
                for j in sensors:
                    eff, row = make(j), per_sensor[j - 1]
                    if not eff.applies or any(eff.label == o.label or eff.label in o.supersedes
                                              for o in row):
                        continue
                    # a larger form of an effect already there replaces it (aux_poly > aux)
                    row[:] = [o for o in row if o.label not in eff.supersedes]
                    clash = [o for o in row if {o.name, o.label} & set(eff.excludes)
                             or {eff.name, eff.label} & set(o.excludes)]
                    if clash:
                        raise ValueError(
                            f'{eff.label} and {clash[0].label} on sensor {j} describe the same '
                            f'degrees of freedom ({eff.label}: {eff.describe()}; '
                            f'{clash[0].label}: {clash[0].describe()}); use one or the other')
                    row.append(eff)
        for row in per_sensor:
            row.sort(key=lambda e: (e.kind != 'linear', e.linear_order))
        return cls(per_sensor, array_effects, formula.drops)

    def spec(self):
        """Canonical list of effect tokens (``name`` or ``name@j``)."""
        out = []
        labels = [[e.label for e in row] for row in self.effects]
        first = {}                            # label -> one instance
        for eff in (e for row in self.effects for e in row):
            first.setdefault(eff.label, eff)
        for lab, eff in first.items():
            have = [j + 1 for j, row in enumerate(labels) if lab in row]
            expected = list(range(1 if eff.on_sensor1 else 2, self.n_sensors + 1))
            if have == expected or getattr(eff, 'shared', False):
                out.append(lab)
            else:
                out.extend(f'{lab}@{j}' for j in have)
        from magcal_ros.core.effects.base import format_arg
        return out + [e.label for e in self.array_effects] + [
            f'drop({format_arg(a)}, {format_arg(b)})' + (
                '' if who is None else f'@{who[0]}' if len(who) == 1
                else '@{' + ','.join(map(str, who)) + '}')
            for a, b, who in self.drops]

    def with_effect(self, token):
        """Return a new model with ``token`` added; the array effects keep their references."""
        new = Model.from_spec(self.spec() + [token], self.n_sensors)
        _copy_refs(self.array_effects, new.array_effects)
        return new

    def take_refs(self, other):
        """Give this model's effects the references of ``other``'s effects of the same label."""
        for row_s, row_d in zip(other.effects, self.effects):
            _copy_refs(row_s, row_d)
        _copy_refs(other.array_effects, self.array_effects)
        return self

    def reading_mask(self, t):
        """Return (S, N) bool: the readings at times ``t`` (N,) s the ``drop`` terms keep."""
        t = np.asarray(t, float)
        keep = np.ones((self.n_sensors, len(t)), bool)
        for a, b, who in self.drops:
            inside = (t >= a) & (t <= b)
            rows = slice(None) if who is None else [j - 1 for j in who]
            keep[rows] &= ~inside
        return keep

    def fit_mask(self, t):
        """Return (N,) bool: the sets at times ``t`` (N,) s that keep a reading."""
        return self.reading_mask(t).any(axis=0)

    def has(self, j, name):
        """Return True if sensor j has an effect with this label or name."""
        return any(e.label == name or e.name == name for e in self.effects[j - 1])

    def frame_rotation(self, j):
        """Return True if sensor j has an effect holding its rotation into the array frame."""
        return any(e.frame_rotation for e in self.effects[j - 1])

    @property
    def joint(self):
        """Whether the sensors share one field per epoch (array-wide effect, frame rotation)."""
        return self.n_sensors > 1 and (
            bool(self.array_effects) or bool(self.shared_slices)
            or any(self.frame_rotation(j) for j in range(2, self.n_sensors + 1)))

    @property
    def sensor_groups(self):
        """Sensors fitted together (1-based): all of them when :attr:`joint`, else one each."""
        s = self.n_sensors
        return [list(range(1, s + 1))] if self.joint else [[j] for j in range(1, s + 1)]

    def default_params(self):
        """(n_params,) parameters of ideal sensors."""
        p = np.zeros(self.n_params)
        for _, eff, sl in self.effect_slices():
            p[sl] = eff.default_params()
        return p

    def param_info(self):
        """List of (sensor, effect label, name, unit) for each parameter."""
        out = [None] * self.n_params
        for j, eff, sl in self.effect_slices():
            # sensor 0: the array, and a parameter set shared by every sensor (@alike)
            who = 0 if getattr(eff, 'shared', False) else j
            for i, nm, un in zip(range(sl.start, sl.stop), eff.param_names, eff.units):
                out[i] = (who, eff.label, nm, un)
        return out

    def param_positions(self):
        """{(sensor, effect label, name): index} of every parameter (:meth:`param_info`)."""
        return {k[:3]: i for i, k in enumerate(self.param_info())}

    def _in_contexts(self, contexts):
        """[(effect, its context, its name)]: the sensors' effects, the array's (sensor 1's)."""
        out = [(e, c, f'{e.label}@{e.sensor}') for row, c in zip(self.effects, contexts)
               for e in row]
        return out + [(e, contexts[0], e.label) for e in self.array_effects] if contexts else out

    def prepare(self, contexts):
        """Let effects compute their reference values (mean temperature, t0, ...)."""
        for eff, ctx, _ in self._in_contexts(contexts):
            eff.prepare(ctx)

    def check(self, contexts):
        """Reasons why effects cannot be excited by the data (empty list if all fine)."""
        return [f'{name}: {why}' for eff, ctx, name in self._in_contexts(contexts)
                if (why := eff.check(ctx))]

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

    def array_shift(self, j, p, ctx, b=None):
        """(N, 3) nT field at sensor j minus the centre field ``b`` (N, 3) nT, when given."""
        out = np.zeros((len(ctx.t), 3))
        for eff, sl in zip(self.array_effects, self.array_slices):
            if not getattr(eff, 'reads_field', False):
                out = out + eff.shift(p[sl], ctx, j)
            elif b is not None:
                out = out + eff.shift(p[sl], ctx, j, b)
        return out

    def forward(self, j, p, b, ctx, a=None, add=None):
        """Raw reading (N, 3) nT of sensor j in field b (N, 3) nT; a, add: A_j, fixed_additive."""
        if self.array_effects:
            b = b + self.array_shift(j, p, ctx, b)
        lin = b @ (self.matrix(j, p) if a is None else a).T
        return lin + (self.additive(j, p, ctx, lin) if add is None else add)

    def fixed_additive(self, j, p, ctx, n):
        """Return (n, 3) nT :meth:`additive` of sensor j at p, or None when it reads the field."""
        if any(e.depends_on_lin() for e in self.effects[j - 1] if e.kind != 'linear'):
            return None
        return self.additive(j, p, ctx, np.zeros((n, 3)))

    def forward_differences(self, j, p, b, ctx, cols, base=None):
        """
        Return (diff, h): forward differences of sensor j's reading in the parameters ``cols``.

        ``diff`` (len(cols), N, 3) nT forward(p + h_i e_i) - forward(p) at the field ``b``
        (N, 3) nT, ``h`` 1e-6 max(1, |p_i|); ``base`` (N, 3) nT forward(p) if known.  Only
        what a parameter changes is evaluated again.
        """
        h = np.array([1e-6 * max(1.0, abs(p[i])) for i in cols])
        owner, linear = {}, set()
        reading = []                    # additive effects that read the linear part
        for eff, sl in zip(self.effects[j - 1], self.slices[j - 1]):
            if eff.kind != 'linear':
                owner.update({i: (eff, sl) for i in range(sl.start, sl.stop)})
                if eff.depends_on_lin():
                    reading.append((eff, sl))
            else:
                linear.update(range(sl.start, sl.stop))
        lin, contrib = None, {}
        diff = np.empty((len(cols), len(b), 3))
        for c, i in enumerate(cols):
            pp = p.copy()
            pp[i] += h[c]
            if (i in owner or i in linear) and lin is None:
                bb = b + self.array_shift(j, p, ctx, b) if self.array_effects else b
                a0 = self.matrix(j, p)
                lin = bb @ a0.T
            if i in owner:
                eff, sl = owner[i]
                if sl.start not in contrib:
                    contrib[sl.start] = eff.contribution(p[sl], ctx, lin)
                np.subtract(eff.contribution(pp[sl], ctx, lin), contrib[sl.start], out=diff[c])
            elif i in linear:
                np.matmul(bb, (self.matrix(j, pp) - a0).T, out=diff[c])
                for eff, sl in reading:
                    if sl.start not in contrib:
                        contrib[sl.start] = eff.contribution(p[sl], ctx, lin)
                    diff[c] += eff.contribution(p[sl], ctx, lin + diff[c]) - contrib[sl.start]
            else:
                if base is None:
                    base = self.forward(j, p, b, ctx)
                np.subtract(self.forward(j, pp, b, ctx), base, out=diff[c])
        return diff, h

    def correct(self, j, p, raw, ctx, n_iter=4, a_inv=None):
        """Invert :meth:`forward` (by fixed point where it reads lin): (N, 3) nT; a_inv: A_j^-1."""
        raw = np.asarray(raw, float)
        if a_inv is None:
            a_inv = np.linalg.inv(self.matrix(j, p))
        lin = raw - self.additive(j, p, ctx, raw)
        if any(e.depends_on_lin() for e in self.effects[j - 1]):
            for _ in range(n_iter):
                lin = raw - self.additive(j, p, ctx, lin)
        return lin @ a_inv.T

    def axis_map(self, j):
        """(3, 3) signed permutation of sensor j's ``axes(...)`` effect, identity without."""
        for eff in self.effects[j - 1]:
            if isinstance(eff, fx.AxisMap):
                return eff.map
        return np.eye(3)

    def params_from_linear(self, j, a, o, p=None):
        """
        Return p with sensor j's linear and offset parameters set from A (3, 3) and o (3,) nT.

        M^T A = U Q (M the axis map; paper 004 eq. 2-3): each effect takes its share.
        """
        p = self.default_params() if p is None else p.copy()
        a = self.axis_map(j).T @ np.asarray(a, float)
        parts = fx.decompose_linear(a, o)
        for eff, sl in zip(self.effects[j - 1], self.slices[j - 1]):
            share = eff.params_from_linear(parts)
            if share is not None:
                p[sl] = share
        return p


def _copy_refs(source, dest):
    """Give each effect of ``dest`` a copy of the references of its label in ``source``."""
    refs = {e.label: e.refs for e in source}
    for e in dest:
        if e.label in refs:
            e.refs = dict(refs[e.label])


def data_hash(data):
    """SHA-256 of the raw readings and times (provenance)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data.t).tobytes())
    h.update(np.ascontiguousarray(data.raw).tobytes())
    return h.hexdigest()
