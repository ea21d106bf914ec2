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
Candidate effects of the diagnosis: the tokens to test, where they come from, their evidence.

The catalog (:func:`candidate_tokens`), the residual's steps and lines
(:func:`propose_from_residual`), the findings' tokens (:func:`tokens_from_findings`);
:func:`split_testable` sets aside, with the reason, those the data cannot excite.
"""
from dataclasses import dataclass
import math

from magcal_ros.core import effects as fx
from magcal_ros.core.discovery.constants import NESTED
from magcal_ros.core.discovery.findings import KINDS
from magcal_ros.core.discovery.measures import binary_segmentation, periodogram
import numpy as np


@dataclass(frozen=True, eq=False)
class Candidate:
    """
    Evidence for adding one effect to the model (all RMS values in nT).

    ``token``: model-spec token ('temperature@2'; without '@' on all sensors), ``effect`` its
    label; ``sensor``: 1-based, None when added to every sensor; ``n_params``: parameters
    added (k of the likelihood-ratio test); ``rms_before_nt``, ``rms_after_nt``,
    ``vector_rms_before_nt``, ``vector_rms_after_nt``: scalar and vector (vs sensor 1) RMS of
    the affected sensors without and with the effect (after: None when not evaluated);
    ``delta_chi2``, ``delta_bic``, ``p_value``, ``log10_p_value``: decrease of chi-square
    (noise levels fixed), -delta_chi2 + k ln(n_obs), and the likelihood-ratio test
    (chi-square, k degrees of freedom); ``method``: 'refit' (full ML refit), 'one-step' (one
    Gauss-Newton step, evaluated), 'score' (the decrease that step predicts, not evaluated;
    also a term of the formula search), 'search' (the search's term that is the verdict) or
    'localised' (a ``drop``); ``cv_rms_before_nt``, ``cv_rms_after_nt``: combined held-out
    RMS (None when not computed); ``significant``: p below the Bonferroni threshold, delta
    BIC < -10 and at least MIN_EXPLAINED; ``params``: tuple of the added parameters' dicts
    {sensor, name, unit, value} after the fit; ``explained_fraction``, ``decided_by``: share
    (0..1) of the combined excess mean square over the floor removed, and by which measure
    ('held-out' or 'in-sample (...)'), or None; ``note``: why a candidate with a good fit is
    not adopted (``Effect.reduces``), or None; ``hideable_rms_nt``: RMS per axis, nT, of the
    largest effect of this kind the test would miss because the base's own parameters absorb
    it over this record's motion (inf: some combination at any size; :func:`.screen.absorbed`),
    None when not screened.
    """

    token: str
    effect: str
    sensor: int | None
    n_params: int
    rms_before_nt: float
    rms_after_nt: float | None
    vector_rms_before_nt: float | None
    vector_rms_after_nt: float | None
    delta_chi2: float
    delta_bic: float
    p_value: float
    log10_p_value: float
    method: str
    cv_rms_before_nt: float | None = None
    cv_rms_after_nt: float | None = None
    significant: bool = False
    params: tuple = ()
    explained_fraction: float | None = None
    decided_by: str | None = None
    note: str | None = None
    hideable_rms_nt: float | None = None

    def to_dict(self):
        """JSON-ready dict (docs/design.md §2 keys first)."""
        return {**{k: getattr(self, k) for k in _KEYS}, 'params': [dict(p) for p in self.params]}


#: the keys of :meth:`Candidate.to_dict` but ``params``, in order
_KEYS = ('effect', 'sensor', 'rms_before_nt', 'rms_after_nt', 'delta_bic', 'p_value', 'token',
         'n_params', 'vector_rms_before_nt', 'vector_rms_after_nt', 'delta_chi2',
         'log10_p_value', 'cv_rms_before_nt', 'cv_rms_after_nt', 'significant', 'method',
         'explained_fraction', 'decided_by', 'note', 'hideable_rms_nt')


def candidate_tokens(model, data, extra=()):
    """
    Every effect not in ``model``, per sensor where it applies and on all sensors at once.

    Returns [(token, effect label, sensor or None)], without those that clash with the model
    (:data:`NESTED`, ``Effect.excludes``); effects with arguments with ``suggest_args``' and
    the ``extra`` names (``step(300)``); an additive effect free on every sensor also on all.
    """
    s = model.n_sensors
    ctx = data.context(1)
    names = []
    for n in fx.registered_effects():
        if n != 'aux:<column>':
            names += ([f'{n}({",".join(a)})' for a in fx.effect_class(n).suggest_args(ctx)]
                      if fx.needs_args(n) else [n])
    names += ['aux:' + c for c in sorted(data.aux)]
    names += [e for e in extra if e not in names]
    out = []
    for name in names:
        if getattr(fx.effect_class(name), 'scope', 'sensor') == 'array':
            # one effect of the whole array (site_gradient): needs paper 004's cross
            eff = fx.make_effect(name, 0)
            if (name not in {e.name for e in model.array_effects} and s >= 3
                    and getattr(eff, 'candidate', True)
                    and (s == 4 or not hasattr(eff, 'set_positions'))
                    and all(data.context(1).has(sig) for sig in eff.signals)):
                out.append((name, name, None))
            continue
        free = []
        additive = False
        for j in range(1, s + 1):
            try:
                eff = fx.make_effect(name, j)
            except ValueError:
                continue
            if not eff.applies:
                continue
            additive = eff.kind != 'linear'
            row = model.effects[j - 1]
            present = {e.label for e in row} | {e.name for e in row}
            if (eff.label in present or any(o in present for o in NESTED.get(eff.name, ()))
                    or any(x in present for x in eff.excludes)
                    or any(eff.name in e.excludes or eff.label in e.excludes for e in row)):
                continue
            free.append(j)
            out.append((f'{eff.label}@{j}', eff.label, j))
        if s > 1 and len(free) == s and additive:
            out.append((eff.label, eff.label, None))
    return out


def token_label(tok):
    """(effect label, sensor or None) of a model-spec token."""
    name, args, sensor = fx.parse_token(tok)
    full = f'{name}({",".join(args)})' if args else name
    return fx.make_effect(full, sensor or 1).label, sensor


def propose_from_residual(t, residual, max_steps=2, min_line_ratio=30.0):
    """
    Effects with arguments suggested by the residual: offset steps and periodic lines.

    ``t`` (N,) s; ``residual`` (S, N, 3) raw-space residual, nT; ``max_steps``: change points;
    ``min_line_ratio``: a line's power over the median power (white noise: ~1e-5 in ~1e4 bins
    at 30).  Returns names, e.g. ['step(300)', 'periodic(0.23)'] (:func:`residual_features`).
    """
    t = np.asarray(t, float)
    found, lines = residual_features(t, residual, max_steps, min_line_ratio)
    if len(t) < 50:
        return []
    dt = float(np.median(np.diff(t)))
    # the first sample after the change, to the sampling interval's decimal
    decimals = max(0, -math.floor(math.log10(dt))) if dt > 0 else 0

    def at(k):        # all the integer digits: a clock since 1970 keeps its fraction
        return f'{t[k]:.{decimals}f}'.rstrip('0').rstrip('.') if decimals else f'{t[k]:.0f}'
    out = [f'step({at(k)})' for k in sorted(found)]
    if len(found) > 1:
        out.append('step(' + ','.join(at(k) for k in sorted(found)) + ')')
    if lines:
        _, fbest = max(lines.values())
        out.append(f'periodic({fbest:.5g})')
    return out


def residual_features(t, residual, max_steps=2, min_line_ratio=30.0, readings=None):
    """
    Change points and spectral lines of a residual (see :func:`propose_from_residual`).

    Changes: binary segmentation of the sensors' residuals together, and with ``readings``
    (S, N, 3) nT of the products r_a u_b (u = m / |m|), where a step of a gain shows.  Lines:
    each sensor's periodogram peak, refined on a grid 10x finer than 1/span.  Returns (sorted
    epoch indices after each change, {sensor index: (peak / median power, frequency Hz)}).
    """
    t = np.asarray(t, float)
    n = len(t)
    if n < 50:
        return [], {}
    r = residual - residual.mean(axis=1, keepdims=True)
    # a change is kept far above white noise's C (10 + 5 ln N) (a split's ~ chi2(C) there)

    def changes(x):
        return binary_segmentation(x, max_steps, x.shape[1] * (10.0 + 5.0 * math.log(n)))
    found = changes(r.transpose(1, 0, 2).reshape(n, -1))              # (N, 3S)
    if readings is not None:
        lin = _gain_products(residual, readings)                         # (S, N, 3, 3)
        lin = lin - lin.mean(axis=1, keepdims=True)
        # a change point of the gains near one of the mean's is the same change
        tol = max(3, n // 100)
        for k in changes(lin.transpose(1, 0, 2, 3).reshape(n, -1)):    # (N, 9S)
            if all(abs(k - f) > tol for f in found):
                found.append(k)
    # -- lines: each sensor's strongest, over the median power
    span = float(t[-1] - t[0])
    if span <= 0:
        return sorted(found), {}
    f_lo, f_hi = 5.0 / span, 0.5 / float(np.median(np.diff(t)))
    lines = {}
    for j in range(r.shape[0]):
        freqs, power, _ = periodogram(t, r[j], oversample=8)
        keep = (freqs >= f_lo) & (freqs < 0.98 * f_hi)
        if keep.sum() < 20:
            continue
        fs, ps = freqs[keep], power[keep].sum(axis=1)
        i = int(np.argmax(ps))
        if ps[i] < min_line_ratio * np.median(ps):
            continue
        grid = fs[i] + np.linspace(-1.0, 1.0, 41) / span
        tt = t - t[0]
        pw = [np.sum(np.abs(np.exp(-2j * np.pi * g * tt) @ r[j]) ** 2) for g in grid]
        fbest = float(grid[int(np.argmax(pw))])
        lines[j] = (ps[i] / np.median(ps), fbest)
    return sorted(found), lines


def _gain_products(residual, readings):
    """(S, N, 3, 3) products r_a u_b of a residual and its reading's direction u = m / |m|."""
    m = np.asarray(readings, float)
    norm = np.linalg.norm(m, axis=2, keepdims=True)
    u = np.divide(m, norm, out=np.zeros_like(m), where=norm > 0)
    return np.asarray(residual, float)[:, :, :, None] * u[:, :, None, :]


def demodulated_lines(t, residual, readings, min_line_ratio=30.0):
    """
    Sorted frequencies (Hz) of lines modulating the gains: in the products r_a u_b.

    A modulated map leaves dM(t) m, side bands at f +- the turn rates; r_a u_b (u = m / |m|)
    averages to dM(t) |m| / 3, the line at f.  ``residual``, ``readings``: (S, N, 3) nT.
    """
    prod = _gain_products(residual, readings)
    _, lines = residual_features(t, prod.reshape(*prod.shape[:2], 9), max_steps=0,
                                 min_line_ratio=min_line_ratio)
    return sorted({round(f, 6) for _, f in lines.values()})


def extend_model(model, params, token, contexts):
    """
    ``model`` with ``token`` added, its parameters carried over, the new ones at default.

    Returns (new model, (P',) parameters, (P',) bool mask of the added parameters).
    """
    new = model.with_effect(token)
    new.take_refs(model)
    new.prepare(contexts)
    p = new.default_params()
    old = {info[:3]: v for info, v in zip(model.param_info(), params)}
    for j, row in enumerate(new.effects, start=1):
        for e in row:            # an effect that replaces another takes over its values
            for lab in e.supersedes:
                old.update({(s_, e.label, n): v for (s_, l_, n), v in list(old.items())
                            if s_ == j and l_ == lab})
    keys = [info[:3] for info in new.param_info()]
    added = np.array([k not in old for k in keys], bool)
    for i in np.flatnonzero(~added):
        p[i] = old[keys[i]]
    return new, p, added


def sensors_of(sensor, n_sensors):
    """Return the 1-based sensors a candidate acts on (``sensor`` None: all of them)."""
    return list(range(1, n_sensors + 1)) if sensor is None else [sensor]


def added_params(model, p, added):
    """Return the parameters flagged in ``added`` as dicts {sensor, name, unit, value}."""
    info = model.param_info()
    return tuple({'sensor': s, 'name': n, 'unit': u, 'value': float(p[i])}
                 for i, (s, _, n, u) in enumerate(info) if added[i])


def split_testable(model, tokens, contexts):
    """
    Split (token, label, sensor) into ([testable ones], [(token, why not)]).

    Why not: ``Effect.check`` on ``contexts`` (one per sensor) fails, the model refuses the
    effect, has it already, or it would tie the sensors to one field.
    """
    s = model.n_sensors
    testable, not_testable = [], []
    for tok, label, sensor in tokens:
        why = None
        for j in sensors_of(sensor, s):
            why = fx.make_effect(label, j).check(contexts[j - 1])
            if why:
                break
        if why is None:
            try:
                trial = model.with_effect(tok)
            except ValueError as exc:
                why = str(exc)
            else:
                if trial.n_params == model.n_params:
                    why = 'already in the model'
                elif trial.joint != model.joint:
                    why = ('ties the sensors to one field (a different likelihood): fit '
                           f'--model {",".join(trial.spec())} and compare the vector residual')
        (not_testable.append((tok, why)) if why else testable.append((tok, label, sensor)))
    return testable, not_testable


def reads_stderr(model, label):
    """Tell whether the fit's uncertainties matter to ``label``'s own ``Effect.reduces``."""
    return any(type(eff).reduces is not fx.Effect.reduces
               for row in model.effects for eff in row if eff.label == label)


def reduces_to_simpler(model, p, stderr, label, contexts):
    """Return the first reason the added effect's fit reduces it to a simpler one, or None."""
    for j, row in enumerate(model.effects):
        for eff, sl in zip(row, model.slices[j]):
            if eff.label == label:
                why = eff.reduces(p[sl], None if stderr is None else stderr[sl], contexts[j])
                if why:
                    return f'sensor {j + 1}: {why}'
    return None


def tokens_from_findings(findings):
    """
    Names with arguments the findings (dicts) point to: their token, else their kind's.

    Tokens without arguments are among the catalog's candidates already.
    """
    out = []
    for fd in findings:
        tok, kind = fd.get('token'), KINDS.get(fd.get('kind'))
        if not tok and kind is not None:
            tok = kind.token(fd.get('value'), fd.get('channel'), {}, '')
        try:
            name, args, _ = fx.parse_token(tok or '')
        except ValueError:
            continue
        if args:
            out.append(f'{name}({",".join(args)})')
    return list(dict.fromkeys(out))
