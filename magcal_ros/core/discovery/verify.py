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
Every term the diagnosis offers is fitted first, as ``magcal fit`` would fit it (issue 32).

The screen, the refits and the search judge a term linearised or without the
identifiability check; :func:`verify_term` runs ``magcal fit``'s fit (warm-started, the
diagnosis' robust and constrained settings) and the held-out test.  A term is offered only
when the fit accepts it, converges and removes :data:`~.constants.MIN_EXPLAINED` of the
held-out excess over the floor; else the reason is shown.  A ``drop`` is judged on the
epochs it keeps.
"""
from dataclasses import dataclass, replace

from magcal_ros.core.discovery.candidates import extend_model
from magcal_ros.core.discovery.constants import (MAX_FINDING_TRIES, MAX_VERDICT_TRIES,
                                                 MIN_DELTA_BIC, MIN_EXPLAINED, SPLIT_SHARE)
from magcal_ros.core.discovery.measures import dof_factor, evaluate_residuals, explained_share
from magcal_ros.core.discovery.validation import cross_validate
from magcal_ros.core.effects.safety import first_line
from magcal_ros.core.model.fitting import fit
import numpy as np


@dataclass(frozen=True)
class Verified:
    """
    A term fitted with the diagnosed model as ``magcal fit`` fits it.

    ``ok``: it passes; ``reason``: why not, or the figures; ``rms_before_nt``,
    ``rms_after_nt``: combined held-out (else in-sample) RMS, nT; ``share``: of the excess.
    """

    token: str
    ok: bool
    reason: str
    rms_before_nt: float | None = None
    rms_after_nt: float | None = None
    share: float | None = None


def verify_term(b, token, cv0, folds, cv_method='newton', on_degenerate='raise',
                replaces=(), start=None):
    """
    Fit ``token`` with the diagnosed model and test it held out: a :class:`Verified`.

    ``b``: the diagnosed fit (run._Base); ``cv0``: :func:`cross_validate` of the diagnosed
    model (None: in-sample) with ``folds`` and ``cv_method``; ``replaces``: terms ``token``
    takes the place of (then fitted from the closed form); ``start``: values of the
    parameters the term adds.
    """
    try:
        if replaces:
            from magcal_ros.core.model import Model
            m_ext = Model.from_spec([t for t in b.model.spec() if t not in set(replaces)]
                                    + [token], b.model.n_sensors)
            m_ext.prepare(b.contexts)
            p_ext = None
        else:
            m_ext, p_ext, added = extend_model(b.model, b.params, token, b.contexts)
            if start is not None and len(start) == int(added.sum()):
                p_ext[added] = start
    except ValueError as exc:
        return Verified(token, False, f'the model does not take it: {first_line(exc)}')
    kw = {'f_scale': b.f_scale} if b.robust else {}
    try:
        r = fit(b.data, m_ext, field_nt=b.f, init=p_ext, robust=b.robust,
                constrained=b.constrained, extra_priors=b.carried_priors(m_ext),
                on_degenerate=on_degenerate, **kw)
    except ValueError as exc:
        return Verified(token, False, f'magcal fit refuses it: {first_line(exc)}')
    except np.linalg.LinAlgError as exc:
        return Verified(token, False, f'the fit fails: {exc}')
    if not r.success:
        return Verified(token, False, f'the fit does not converge ({r.message})')
    # a drop() leaves epochs out: the model with it is judged on the epochs it keeps
    data, f, contexts = b.data, b.f, b.contexts
    if getattr(m_ext, 'drops', ()):
        keep = np.flatnonzero(m_ext.fit_mask(b.data.t))
        data, f = b.data.subset(keep), b.f[keep]
        contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
        m_ext.prepare(contexts)
    if cv0 is not None:
        before = float(cv0['rms_nt'])
        try:
            cv1 = cross_validate(data, m_ext, r.params, f, b.sigma, folds,
                                 method=cv_method, constrained=b.constrained,
                                 extra_priors=b.carried_priors(m_ext))
        except (ValueError, np.linalg.LinAlgError) as exc:
            return Verified(token, False, f'its held-out test fails: {exc}')
        after = float(cv1['rms_nt'])
        how = 'held-out'
    else:
        before = float(np.sqrt(b.ms0))
        ev = evaluate_residuals(m_ext, r.params, data, f, b.sigma, contexts)
        after = float(np.sqrt(dof_factor(m_ext) * ev.mean_square))
        how = 'in-sample'
    if not np.isfinite(after):
        return Verified(token, False, f'its {how} residual is not finite', before, after)
    share = explained_share(before ** 2, after ** 2, b.floor.value_nt)
    figures = f'{how} RMS {before:.3g} -> {after:.3g} nT'
    why = (f', it raises the {figures}' if after >= before else
           f', it removes only {share:.0%} of the excess over the floor ({figures})'
           if share < MIN_EXPLAINED else f': {figures}')
    return Verified(token, after < before and share >= MIN_EXPLAINED,
                    f'fitted as magcal fit fits it{why}', before, after, share)


def tested_verdict(b, verdict, reason, ranked, cv0, folds, cv_method='newton',
                   on_degenerate='raise', cache=None, p_thr=0.0):
    """
    Keep a verdict only when its term passes :func:`verify_term`; else try the next ones.

    ``ranked``: the candidates, best first; ``cache``: {token: Verified}, filled here;
    ``p_thr``: a candidate below it and the BIC rule may replace a failed verdict.  Returns
    (the first that passes of at most :data:`MAX_VERDICT_TRIES`, or None; its reason; the
    candidates, those that failed not ``significant``, why in ``note``; every Verified).
    """
    cache = {} if cache is None else cache
    if verdict is None:
        return verdict, reason, ranked, []
    order = [verdict] + [c.token for c in ranked if c.token != verdict and (
        c.significant or (c.p_value < p_thr and c.delta_bic < MIN_DELTA_BIC))]
    by_token = {c.token: c for c in ranked}
    tried, chosen = [], None
    for tok in order[:MAX_VERDICT_TRIES]:
        if tok not in cache:
            cand = by_token.get(tok)
            start = ([q['value'] for q in cand.params] if cand is not None and cand.params
                     else None)
            cache[tok] = verify_term(b, tok, cv0, folds, cv_method, on_degenerate, start=start)
        tried.append(cache[tok])
        if cache[tok].ok:
            chosen = cache[tok]
            break
    failed = {v.token: v for v in tried if not v.ok}
    out = [replace(c, significant=False, note=failed[c.token].reason) if c.token in failed
           else c for c in ranked]
    if chosen is not None:
        split = _each_variant(b, chosen, cv0, folds, cv_method, on_degenerate, cache)
        if split is not None:
            v = split[0]
            tried.append(v)
            base = next(c for c in out if c.token == chosen.token)
            first = replace(base, token=v.token, effect=v.token.split('(')[0], sensor=None,
                            params=(), significant=True, explained_fraction=v.share,
                            cv_rms_before_nt=v.rms_before_nt, cv_rms_after_nt=v.rms_after_nt,
                            rms_after_nt=None, vector_rms_after_nt=None, method='refit',
                            decided_by='held-out' if cv0 is not None else 'in-sample', note=None)
            return v.token, f'{reason}; {split[1]}', [first] + out, tried
    if chosen is None:
        why = '; '.join(f'{v.token}: {v.reason}' for v in tried)
        return None, (f'no term passes when fitted with the model as magcal fit fits it '
                      f'({why})'), out, tried
    if chosen.token == verdict:
        return verdict, f'{reason}; {chosen.reason}', out, tried
    # the verdict's candidate first, significant now (its held-out share: verify_term's)
    out = [replace(c, significant=True, explained_fraction=chosen.share,
                   cv_rms_before_nt=chosen.rms_before_nt, cv_rms_after_nt=chosen.rms_after_nt)
           if c.token == chosen.token else c for c in out]
    out.sort(key=lambda c: c.token != chosen.token)
    first = failed[verdict].reason
    return chosen.token, (f'{verdict} is not offered ({first}); the next best, '
                          f'{chosen.token}, {chosen.reason}'), out, tried


def tested_findings(b, found, cv0, folds, cv_method='newton', on_degenerate='raise', cache=None):
    """
    Keep a finding's token only when it passes :func:`verify_term`; else say why.

    At most :data:`MAX_FINDING_TRIES` tokens are fitted, largest effect first.
    """
    cache = {} if cache is None else cache
    if found is None or not any(f.token for f in found.items):
        return found
    budget = MAX_FINDING_TRIES
    for f in sorted((f for f in found.items if f.token),
                    key=lambda f: -(f.explained_fraction or 0.0)):
        if f.token in cache or budget <= 0:
            continue
        cache[f.token] = verify_term(b, f.token, cv0, folds, cv_method, on_degenerate,
                                     replaces=tuple(getattr(f, 'replaces', ()) or ()))
        budget -= 1
    return replace(found, items=tuple(_offered(f, cache.get(f.token) if f.token else None)
                                      for f in found.items))


def _offered(f, v):
    """Return finding ``f``, without its token (and with why) unless ``v`` (Verified) passed."""
    if not f.token or (v is not None and v.ok):
        return f
    why = (f'not fitted, the diagnosis fits at most {MAX_FINDING_TRIES} terms of the findings'
           if v is None else v.reason)
    text = f.text.replace(f' (try {f.token})', '')
    return replace(f, token=None, text=f'{text} ({f.token} is not offered: {why})')


def each_variant(token):
    """Return ``X`` for ``X@alike``, ``scale(d)`` for ``field(d)`` (each sensor's own), or None."""
    t = token.replace(' ', '')
    if t.endswith('@alike') and '+' not in t:
        return token[:token.rindex('@')].rstrip()
    if t.startswith('field(') and t.endswith(')') and '@' not in t and '+' not in t:
        return 'scale(' + token.strip()[len('field('):]
    return None


def _each_variant(b, chosen, cv0, folds, cv_method, on_degenerate, cache):
    """
    Return (Verified, words) of :func:`each_variant` when it passes and does better, or None.

    Better: :data:`SPLIT_SHARE` more of the held-out excess (docs/formulas.md).
    """
    alt = each_variant(chosen.token)
    if alt is None or chosen.share is None:
        return None
    if alt not in cache:
        cache[alt] = verify_term(b, alt, cv0, folds, cv_method, on_degenerate)
    v = cache[alt]
    if not v.ok or v.share is None or v.share < chosen.share + SPLIT_SHARE:
        return None
    return v, (f"the sensors do not follow {chosen.token} alike: with each sensor's own "
               f'parameters, {alt} removes {v.share:.0%} of the held-out excess against '
               f'{chosen.share:.0%} ({v.reason}); {alt} is offered instead')
