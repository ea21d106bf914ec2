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
The diagnosis itself: :func:`diagnose` and its stages.

base fit -> noise floor and findings -> candidate tokens -> one-step screen -> full refit
of the best -> held-out effect size -> ranking -> verdict.  Each stage is one function
below; :func:`diagnose` calls them in order and times them.
"""
from dataclasses import dataclass, replace
import math
import time

from magcal_ros.core.data.noise import data_noise_floor, NoiseFloor
from magcal_ros.core.discovery.candidates import (added_params, Candidate, candidate_tokens,
                                                  demodulated_lines, extend_model,
                                                  propose_from_residual,
                                                  reads_stderr, reduces_to_simpler,
                                                  residual_features,
                                                  sensors_of, split_testable, token_label,
                                                  tokens_from_findings)
from magcal_ros.core.discovery.constants import (ALPHA, AT_FLOOR_RATIO, BLOCKS_PER_FOLD,
                                                 DEFAULT_FOLDS, DEFAULT_MAX_REFIT,
                                                 DEFAULT_MAX_SAMPLES, EVIDENCE_TIE,
                                                 EXPLAINS_SHARE, MIN_BLOCK, MIN_DELTA_BIC,
                                                 MIN_EXPLAINED, REFIT_CHI2_TOL, REFIT_MAX_NFEV,
                                                 REFIT_MORE_NFEV, SCOPE_SHARE,
                                                 SCORE_RULE_OUT_BIC, SEARCH_CHANGE_POINTS,
                                                 SEARCH_LISTED, SEARCH_MAX_EPOCHS,
                                                 STEP_HALVINGS, WHEN_SHARE, WHEN_SPAN)
from magcal_ros.core.discovery.findings import find as find_findings, Finding, KINDS
from magcal_ros.core.discovery.measures import (dof_factor, evaluate_residuals, Evaluation,
                                                explained_share, lag_grid, likelihood_ratio,
                                                n_observations, scalar_rms_of,
                                                soft_l1_lr_loss, vector_rms_of)
from magcal_ros.core.discovery.results import compact_spec, Diagnosis
from magcal_ros.core.discovery.screen import Screen
from magcal_ros.core.discovery.search import search as run_search
from magcal_ros.core.discovery.validation import cross_validate
from magcal_ros.core.discovery.verify import tested_findings, tested_verdict
from magcal_ros.core.effects.base import format_arg
from magcal_ros.core.effects.formula import parse
from magcal_ros.core.model import Model
from magcal_ros.core.model.fitting import fit, fit_epochs, priors_for
from magcal_ros.core.model.solvers import single_threaded_blas
import numpy as np


def report_progress(cb, stage, i, n, label=''):
    """Call ``cb(stage, i, n, label)`` when a progress callback is given."""
    if cb is not None:
        cb(stage, i, n, label)


@dataclass
class Trial:
    """
    A candidate under test: its extended model, parameters and evidence so far.

    ``sensor``: 1-based, None on all; ``model``: the base model with the effect; ``p`` (P',)
    its parameters; ``added`` (P',) bool, those the effect adds; ``ev``: its Evaluation, None
    when the score test ruled it out; ``score_chi2``: the base chi-square less the score
    statistic; ``method``: 'score', 'one-step' or 'refit'; ``reduces``: ``Effect.reduces``'
    reason; ``cv``, ``share``: :func:`cross_validate` and the held-out share of the excess;
    ``start`` (P',): the base parameters with the effect's defaults.
    """

    token: str
    label: str
    sensor: int | None
    model: Model
    p: np.ndarray
    added: np.ndarray
    ev: Evaluation | None
    score_chi2: float
    method: str = 'one-step'
    reduces: str | None = None
    cv: dict | None = None
    share: float | None = None
    start: np.ndarray | None = None
    hideable: float | None = None

    @property
    def k(self):
        """Parameters added (degrees of freedom of the likelihood-ratio test)."""
        return int(self.added.sum())

    @property
    def chi2(self):
        """Its chi-square: ``ev.chi2`` once evaluated, else :attr:`score_chi2`."""
        return self.score_chi2 if self.ev is None else self.ev.chi2


@dataclass
class _Base:
    """The base fit on the tested epochs: what every stage compares a candidate with."""

    data: object            # Dataset, the tested epochs
    f: np.ndarray           # (N,) reference magnitude, nT
    sigma: np.ndarray       # (S,) fixed noise levels, nT
    contexts: list
    model: Model
    params: np.ndarray      # (P,)
    ev0: Evaluation
    floor: NoiseFloor
    loss: object            # chi-square equivalent of the robust loss, or None
    f_scale: float | None   # the robust fit's f_scale, None when not robust
    constrained: bool
    priors: tuple = ()      # the base fit's (index, mean, sd)

    @property
    def robust(self):
        return self.loss is not None

    @property
    def n_obs(self):
        return n_observations(self.model, self.data.n_samples, self.ev0.kept)

    @property
    def ms0(self):
        """Return the combined in-sample mean square of the base fit, nT^2 (readings kept)."""
        return dof_factor(self.model) * self.ev0.mean_square

    def delta_bic(self, trial):
        return -(self.ev0.chi2 - trial.chi2) + trial.k * math.log(self.n_obs)

    def carried_priors(self, model):
        """
        Return the base fit's own priors [(index, mean, sd)] as indices of ``model``.

        Those beyond what ``fit(constrained=...)`` gives ``model`` itself: an attitude-aided
        fit's mounting and IGRF inclination, or a calibration in use's (pipeline.refit_recent),
        so that every refit and held-out fit of the diagnosis holds what the base held.
        """
        where = model.param_positions()
        own = set(priors_for(model, {}, self.constrained))
        base_info = self.model.param_info()
        out = [(where[base_info[i][:3]], m, s) for i, m, s in self.priors
               if base_info[i][:3] in where]
        return [t for t in out if t not in own]


def diagnose(data, model='base', field_nt=None, *, base=None, folds=DEFAULT_FOLDS,
             alpha=ALPHA, max_refit=DEFAULT_MAX_REFIT, candidates=None, progress=None,
             cv_method='newton', max_samples=DEFAULT_MAX_SAMPLES, baseline_m=0.5,
             constrained=False, propose=True, **fit_kwargs):
    """
    Find what the model misses: noise floor, candidate effects ranked, verdict (Diagnosis).

    ``data``: Dataset (S sensors, N epochs) of rotation data in time order, nT; ``model``:
    str or Model to diagnose (ignored when ``base`` is given); ``field_nt``: reference
    magnitude, nT (scalar or (N,); default ``data.ref_total``); ``base``: an existing
    FitResult of the model on ``data`` (default: fitted here); ``folds``: folds of the
    cross-validation (:func:`time_blocks`), 0 (or too short a record): the in-sample share
    decides (``decided_by``); ``alpha``: family-wise significance level (Bonferroni over the
    candidates); ``max_refit``: best-screened candidates refitted in full; ``candidates``:
    tokens to test instead of every missing effect; ``progress``: ``progress(stage, i, n,
    label)`` called as the work proceeds; ``cv_method`` 'newton' or 'refit': how each fold is
    fitted (:func:`cross_validate`); ``max_samples``: test the candidates on at most this
    many evenly spaced epochs (None: all); ``baseline_m``: arm length of a four-sensor cross,
    m (the gradient of a ``nonuniform_field`` finding); ``constrained``: partial attitude
    coverage, every fit with ``fit(constrained=True)``'s priors, held-out fits refitted,
    candidates judged only after a constrained refit; ``propose``: also test the residual's
    steps and lines and the findings' tokens; ``fit_kwargs``: passed to
    :func:`magcal_ros.core.model.fit` for the base fit.
    """
    with single_threaded_blas():
        t_start = time.perf_counter()
        seconds = {}
        f = data.reference_magnitude(field_nt)
        base = _base_fit(data, model, f, base, constrained, progress, fit_kwargs)
        seconds['base_fit'] = time.perf_counter() - t_start
        floor = data_noise_floor(data, base)
        t0 = time.perf_counter()
        found = find_findings(data, base, baseline_m=baseline_m)   # model-free, all epochs
        seconds['findings'] = time.perf_counter() - t0
        b = _prepare(data, f, base, floor, max_samples, constrained)
        scalar_rms, vector_rms, at_floor = _base_measures(b)

        tokens = _candidate_tokens(b, candidates, propose, found)
        testable, not_testable = split_testable(b.model, tokens, b.contexts)
        p_thr = alpha / max(1, len(testable))

        t0 = time.perf_counter()
        trials, screen = _screen(b, testable, progress)
        seconds['screen'] = time.perf_counter() - t0
        t0 = time.perf_counter()
        n_refit = _refit(b, trials, screen, max_refit, p_thr, progress)
        seconds['refit'] = time.perf_counter() - t0
        t0 = time.perf_counter()
        held_out = bool(folds) and b.data.n_samples >= folds * BLOCKS_PER_FOLD * MIN_BLOCK
        cv0 = _held_out(b, trials, n_refit, folds, cv_method, p_thr, progress, held_out)
        seconds['cross_validate'] = time.perf_counter() - t0

        n = b.data.n_samples
        decided = ('held-out' if held_out else
                   'in-sample' + (' (folds=0)' if not folds else
                                  f' (record of {n} epochs too short for {folds} folds)'))
        ranked = _rank(b, trials, cv0, held_out, decided, p_thr)
        verdict, reason = _verdict(b, ranked, _ratio(floor, scalar_rms, vector_rms), at_floor,
                                   held_out, p_thr)
        # the formula search: only when something is missing
        found_terms = None
        if candidates is None and propose and not b.robust and not constrained and not at_floor:
            t0 = time.perf_counter()
            found_terms = _search(b, screen, alpha)
            seconds['search'] = time.perf_counter() - t0
            verdict, reason, ranked = _merge_search(b, trials, ranked, verdict, reason,
                                                    found_terms, at_floor)
        # every term offered is first fitted as `magcal fit` fits it (verify.py)
        t0 = time.perf_counter()
        tested = {}
        on_deg = fit_kwargs.get('on_degenerate', 'raise')
        verdict, reason, ranked, _ = tested_verdict(b, verdict, reason, ranked, cv0, folds,
                                                    cv_method, on_deg, tested, p_thr)
        if found is not None and not at_floor and found_terms is not None:
            found = _describe(b, found, found_terms, verdict, scalar_rms, vector_rms)
        found = tested_findings(b, found, cv0, folds, cv_method, on_deg, tested)
        if verdict is None and not at_floor:
            reason = _stop_reason(reason, found)
        seconds['verify'] = time.perf_counter() - t0
        seconds['total'] = time.perf_counter() - t_start
        return Diagnosis(
            model=tuple(compact_spec(b.model)), n_samples=data.n_samples, n_used=n,
            n_sensors=b.data.n_sensors, n_params=b.model.n_params,
            noise_floor=floor, scalar_rms_nt=scalar_rms, vector_rms_nt=vector_rms,
            residual_rms_nt=float(np.sqrt(b.ms0)),
            cv_rms_nt=None if cv0 is None else cv0['rms_nt'],
            at_floor=bool(at_floor), candidates=tuple(ranked), not_testable=tuple(not_testable),
            verdict_token=verdict, verdict_reason=reason, p_threshold=p_thr, folds=folds,
            seconds=seconds, result=base, findings=found, decided_by=decided,
            excess_ms_nt2=float(b.ms0 - floor.value_nt ** 2))


def _search(b, screen, alpha):
    """Run the formula search (:mod:`.search`) on the base fit's residual; SearchResult."""
    data, resid, n_obs = b.data, b.ev0.residual, b.n_obs
    if data.n_samples > SEARCH_MAX_EPOCHS:
        keep = fit_epochs(data.n_samples, SEARCH_MAX_EPOCHS)
        data, resid = data.subset(keep), resid[:, keep]
        kept = None if b.ev0.kept is None else b.ev0.kept[:, keep]
        n_obs = n_observations(b.model, len(keep), kept)
        screen = Screen(b.model, b.params, data.raw, [c.subset(keep) for c in b.contexts],
                        b.f[keep], b.sigma, b.priors, b.constrained)
    elif screen is None:
        screen = Screen(b.model, b.params, data.raw, b.contexts, b.f, b.sigma, b.priors,
                        b.constrained)
    t = data.t
    cps, lines = residual_features(t, resid, max_steps=SEARCH_CHANGE_POINTS, readings=data.raw)
    times = [float(t[k]) for k in cps]
    steps = [(x,) for x in times] + ([tuple(times)] if len(times) > 1 else [])
    span = float(t[-1] - t[0])
    windows = [(a, c) for a, c in zip(times[:-1], times[1:]) if c - a < 0.5 * span]
    freqs = sorted({round(f, 6) for _, f in lines.values()}
                   | set(demodulated_lines(t, resid, data.raw)))
    return run_search(data, resid, screen, b.sigma, b.floor, n_obs, alpha=alpha,
                      steps=steps, windows=windows, lines=freqs)


def _ratio(floor, scalar_rms, vector_rms):
    """Return the largest RMS / floor of {sensor: scalar RMS} and {sensor: vector RMS}, nT."""
    return max([v / floor.per_sensor_nt[j - 1] for j, v in scalar_rms.items()]
               + [v / floor.vector_floor_nt(j) for j, v in vector_rms.items()])


def _rms_of(ev, s):
    """Return ({j: scalar RMS}, {j > 1: vector RMS vs sensor 1}) of an Evaluation, nT."""
    return ({j: ev.scalar_rms(j) for j in range(1, s + 1)},
            {j: ev.vector_rms(j) for j in range(2, s + 1)})


def _merge_search(b, trials, ranked, verdict, reason, res, at_floor):
    """
    Put the search's terms among the candidates and choose the verdict between the two.

    The catalog's verdict stands when it brings every sensor to its floor, unless the search's
    term does too on fewer sensors; otherwise the search's term wins when it leaves less.
    When nothing explains the excess, an excess confined in time is left out instead.
    """
    s = b.data.n_sensors
    if at_floor:
        return verdict, reason, ranked
    adopted = res.adopted
    cat = next((c for c in trials if c.token == verdict), None) if verdict else None
    c_ratio = (None if cat is None or cat.ev is None else
               _ratio(b.floor, *_rms_of(cat.ev, b.data.n_sensors)))
    a_ratio = None if adopted is None else max(adopted.ratios.values())
    c_expl = cat is not None and c_ratio is not None and c_ratio <= AT_FLOOR_RATIO and (
        cat.share is None or cat.share >= EXPLAINS_SHARE)
    a_expl = a_ratio is not None and a_ratio <= AT_FLOOR_RATIO and adopted.share >= EXPLAINS_SHARE
    if not (c_expl or a_expl):
        # nothing explains it: an excess confined in time is left out instead
        loc = res.localised
        if loc is not None:
            cand = _localised_candidate(b, loc)
            why = ('no term brings every sensor to its floor and removes '
                   f'{EXPLAINS_SHARE:.0%} of the excess held out')
            if adopted is not None:
                why += (f' (the best term of the search, {adopted.text_for(s)}, leaves '
                        f'{a_ratio:.2f} x the floor in-sample, {adopted.share:.0%} held out)')
            why += (f'; {loc.share:.0%} of the excess over the floor lies within '
                    f'{format_arg(loc.t0)}-{format_arg(loc.t1)} s on sensor(s) '
                    f'{", ".join(str(j) for j in loc.sensors)}, nothing simple describes '
                    f'it: leave it out (every sensor within '
                    f'{max(loc.ratios_outside.values()):.2f} x its floor outside)')
            return loc.token, why, [cand] + ranked + _listed(b, res, ranked, None)
    if adopted is None:
        return verdict, reason, ranked
    a_text = adopted.text_for(s)
    use_search = (verdict is None or c_ratio is None or (not c_expl and a_ratio < c_ratio)
                  or (a_expl and set(adopted.sensors) < set(sensors_of(cat.sensor, s))))
    if not use_search or (verdict and _same_term(a_text, verdict)):
        # the catalog's token when the search found the composition it stands for
        return verdict, reason, ranked
    top = _term_candidate(b, adopted, res, verdict=True)
    rest = [c for c in ranked if c.token != a_text] + _listed(b, res, ranked, a_text)
    why = (f'formula search over {res.n_generated} candidate terms: delta BIC '
           f'{adopted.delta_bic:.0f}, p = {adopted.p_value:.2g}, removes '
           f'{adopted.share:.0%} of the held-out excess over the floor '
           f'(linearised refit on interleaved time blocks), largest residual / floor after '
           f'{a_ratio:.2f}')
    if verdict:
        why += f'; the best of the catalog, {verdict}, leaves {c_ratio:.2f} x the floor'
    return a_text, why, [top] + rest


def _describe(b, found, res, verdict, scalar_rms, vector_rms):
    """Add the search's 'localised' (``drop(t0, t1)``) and 'unexplained' findings."""
    s = b.data.n_sensors
    new = []
    loc = res.localised
    if loc is not None:
        sens = loc.sensors
        new.append(Finding(
            kind='localised', sensor=sens[0] if len(sens) == 1 else None, channel='t',
            value=float(loc.t1 - loc.t0), unit='s', explained_fraction=float(loc.share),
            text=(f'{_who(sens, s)}: an excess over the floor confined to '
                  f'{format_arg(loc.t0)}-{format_arg(loc.t1)} s ({loc.share:.0%} of it); '
                  f'every sensor within {max(loc.ratios_outside.values()):.2f} x its floor '
                  f'outside: add {loc.token} to leave it out'), token=loc.token))
    if verdict is None:
        left = _what_is_left(b, found, res, scalar_rms, vector_rms)
        if left is not None:
            new.append(left)
    return replace(found, items=tuple(new) + tuple(found.items)) if new else found


def _what_is_left(b, found, res, scalar_rms, vector_rms):
    """
    Describe the excess nothing explains (a Finding of kind 'unexplained'), or None.

    Which sensors carry it, scalar or vector, how far above the floor, when (:func:`_when`)
    and what it follows most (the search's best term or a finding on them, whose token it
    offers).
    """
    s = b.data.n_sensors
    fl = b.floor
    ex = {j: max(v ** 2 - fl.per_sensor_nt[j - 1] ** 2, 0.0) for j, v in scalar_rms.items()}
    vex = {j: max(v ** 2 - fl.vector_floor_nt(j) ** 2, 0.0) for j, v in vector_rms.items()}
    both = {j: ex[j] + vex.get(j, 0.0) for j in ex}
    top = max(both.values()) if both else 0.0
    if top <= 0:
        return None
    sens = tuple(j for j in sorted(both) if both[j] >= SCOPE_SHARE * top)
    scalar = sum(ex[j] for j in sens) >= 0.5 * sum(vex.get(j, 0.0) for j in sens)
    ratio = _ratio(fl, {j: scalar_rms[j] for j in sens},
                   {j: vector_rms[j] for j in sens if j in vector_rms})
    options = []
    best = None if res is None else next((t for t in res.terms if t.delta_chi2 is not None), None)
    if best is not None:
        words = {'time': 'time', 'rate': 'the field rate'}.get(
            best.driver.kind, f'the channel {best.driver.channel}')
        options.append((float(best.share or 0.0), words, best.text_for(s), best.driver.channel))
    for f in found.items:
        words = getattr(KINDS.get(f.kind), 'follows', None)
        if words is not None and (f.sensor is None or f.sensor in sens):
            options.append((float(f.explained_fraction or 0.0), words(f), f.token, f.channel))
    share, follows, token, channel = (max(options, key=lambda o: o[0]) if options else
                                      (0.0, 'nothing the diagnosis tried', None, None))
    return Finding(
        kind='unexplained', sensor=sens[0] if len(sens) == 1 else None, channel=channel,
        value=float(ratio), unit='x floor', explained_fraction=float(share),
        text=(f'{_who(sens, s)}: a {"scalar" if scalar else "vector"} excess of up to '
              f'{ratio:.1f} x the floor {_when(b, sens)} that no term explains; it follows '
              f'{follows} most ({share:.0%} of it)' + ('' if token is None else
                                                       f' (try {token})')), token=token)


def _when(b, sens):
    """Words for when the excess of sensors ``sens`` lies: an interval, or throughout."""
    t = b.data.t
    n = len(t)
    fl = b.floor.per_sensor_nt
    r = b.ev0.residual
    e = sum(np.sum(r[j - 1] ** 2, axis=1) - 3.0 * fl[j - 1] ** 2 for j in sens)
    nb = min(100, max(1, n // 10))
    edges = np.linspace(0, n, nb + 1).round().astype(int)
    blk = np.clip([e[a:c].sum() for a, c in zip(edges[:-1], edges[1:])], 0.0, None)
    total = float(blk.sum())
    if total <= 0 or nb < 4:
        return 'throughout the record'
    cum = np.concatenate([[0.0], np.cumsum(blk)])
    # the shortest run of blocks from each start holding WHEN_SHARE of it; the first shortest
    ends = np.searchsorted(cum, cum[:-1] + WHEN_SHARE * total - 1e-12 * total)
    i = int(np.argmin(np.where(ends <= nb, ends - np.arange(nb), nb + 1)))
    t0, t1 = float(t[edges[i]]), float(t[edges[ends[i]] - 1])
    if t1 - t0 > WHEN_SPAN * float(t[-1] - t[0]):
        return 'throughout the record'
    return f'mostly within {format_arg(t0)}-{format_arg(t1)} s'


def _stop_reason(reason, found):
    """Return the verdict 'none' with what is left (the 'unexplained' finding) and the stop."""
    left = None if found is None else next(
        (f for f in found.items if f.kind == 'unexplained'), None)
    if left is None:
        return reason
    return (f'{reason}. What is left: {left.text}. No term is offered: adding more would '
            'fit the noise or the unknown effect no better held out (a plug-in effect can '
            'describe it, docs/plugins.md)')


def _who(sens, s):
    """Words for a set of sensors: one, an arm of the cross, every sensor, a set."""
    if len(sens) == 1:
        return f'sensor {sens[0]}'
    if len(sens) == s:
        return 'every sensor'
    if s == 4 and set(sens) in ({1, 3}, {2, 4}):
        return f'the arm of sensors {sens[0]} and {sens[1]}'
    return 'sensors ' + ', '.join(str(j) for j in sens)


def _localised_candidate(b, loc):
    """Return a :class:`Candidate` leaving out an excess confined in time (``drop``)."""
    s = b.data.n_sensors
    sens = list(loc.sensors)
    return Candidate(
        token=loc.token, effect='drop', sensor=sens[0] if len(sens) == 1 else None, n_params=0,
        rms_before_nt=scalar_rms_of(b.ev0.scalar, sens, b.ev0.kept), rms_after_nt=None,
        vector_rms_before_nt=vector_rms_of(b.ev0.vector, sens, s, b.ev0.kept),
        vector_rms_after_nt=None, delta_chi2=float('nan'), delta_bic=float('nan'),
        p_value=float('nan'), log10_p_value=float('nan'), method='localised', significant=True,
        explained_fraction=loc.share, decided_by='model-free (excess inside the interval)',
        note=('vector' if loc.vector else 'scalar') + ' excess confined in time')


def _same_term(text, token):
    """Tell whether formula term ``text`` is the composition catalog ``token`` stands for."""
    try:
        term = parse(token).terms[0]
        mine = parse(text).terms[0].text
    except ValueError:
        return False
    forms = [x.replace(' ', '') for x in (mine, term.text, str(term.expansion or ''))]
    return forms[0] in forms[1:]


def _listed(b, res, ranked, verdict):
    """Candidates of the search's best terms not already listed (nor the verdict)."""
    s = b.data.n_sensors
    have = {c.token for c in ranked} | {verdict}
    return [_term_candidate(b, tm, res) for tm in res.terms[:SEARCH_LISTED]
            if tm.text_for(s) not in have]


def _term_candidate(b, tm, res, verdict=False):
    """Return a :class:`Candidate` of a search term (evidence of the linearised problem)."""
    s = b.data.n_sensors
    text = tm.text_for(s)
    sens = list(tm.sensors)
    sensor = sens[0] if len(sens) == 1 else None
    d_chi2 = float(tm.delta_chi2 if tm.delta_chi2 is not None else tm.approx)
    p_val, logp, d_bic = likelihood_ratio(d_chi2, tm.k, b.n_obs)
    after = None
    if tm.ratios:
        after = float(np.sqrt(np.mean([(tm.ratios[j] * b.floor.per_sensor_nt[j - 1]) ** 2
                                       for j in sens])))
    return Candidate(
        token=text, effect=text.split('@')[0], sensor=sensor, n_params=tm.k,
        rms_before_nt=scalar_rms_of(b.ev0.scalar, sens, b.ev0.kept), rms_after_nt=after,
        vector_rms_before_nt=vector_rms_of(b.ev0.vector, sens, s, b.ev0.kept),
        vector_rms_after_nt=None, delta_chi2=d_chi2, delta_bic=d_bic, p_value=p_val,
        log10_p_value=logp, method='search' if verdict else 'score', cv_rms_before_nt=tm.cv_before,
        cv_rms_after_nt=tm.cv_after, significant=verdict, explained_fraction=tm.share,
        decided_by=None if tm.share is None else 'held-out (linearised, search)', note=None)


def order_by_evidence(trials, b):
    """
    Sort ``trials`` in place, lowest delta BIC against ``b`` first.

    Within :data:`EVIDENCE_TIE`: fewer parameters, then a named effect before one with
    arguments, then by token.
    """
    _order_runs(trials, b.delta_bic, lambda c: (c.k, '(' in c.label, c.token))


def _order_runs(items, bic, prefer):
    """Sort ``items`` by ``bic``; runs within EVIDENCE_TIE of their first by ``prefer``."""
    items.sort(key=bic)
    out, i = [], 0
    while i < len(items):
        j = i + 1
        while j < len(items) and bic(items[j]) - bic(items[i]) <= EVIDENCE_TIE:
            j += 1
        out.extend(sorted(items[i:j], key=prefer))
        i = j
    items[:] = out


def _base_fit(data, model, f, base, constrained, progress, fit_kwargs):
    """Return the fit to diagnose: ``base`` as given (checked against ``data``) or fitted here."""
    if base is None:
        if isinstance(model, str):
            model = Model.from_spec(model, data.n_sensors)
        report_progress(progress, 'fit', 0, 1, ','.join(model.spec()))
        base = fit(data, model, field_nt=f, constrained=constrained, **fit_kwargs)
    if base.n_samples != data.n_samples:
        raise ValueError('the base fit was made on other data: pass the same Dataset')
    return base


def _prepare(data, f, base, floor, max_samples, constrained):
    """Return the tested epochs (at most ``max_samples``) and the base fit's residuals on them."""
    n_all = data.n_samples
    keep = fit_epochs(n_all, int(max_samples or 0))     # the fit's own evenly spaced epochs
    model = base.model
    if model.drops:
        # the sets the drop() terms leave out for every sensor are not tested
        keep = keep[model.fit_mask(data.t[keep])]
    if len(keep) < n_all:
        data, f = data.subset(keep), f[keep]
    sigma = np.asarray(base.sigma_nt, float)
    contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    model.prepare(contexts)
    # a robust base fit: likelihood-ratio and BIC for its loss, not as if Gaussian
    loss = f_scale = None
    if bool(getattr(base, 'robust', False)):
        f_scale = float(getattr(base, 'f_scale', 3.0))
        z_all = np.asarray(base.residual_nt) / sigma[:, None, None]
        if getattr(base, 'reading_mask', None) is not None:
            z_all = z_all[base.reading_mask]            # the readings the fit kept
        loss = soft_l1_lr_loss(z_all, f_scale)
    ev0 = evaluate_residuals(model, base.params, data, f, sigma, contexts, loss=loss)
    return _Base(data=data, f=f, sigma=sigma, contexts=contexts, model=model, params=base.params,
                 ev0=ev0, floor=floor, loss=loss, f_scale=f_scale, constrained=constrained,
                 priors=tuple(getattr(base, 'priors', ())))


def _base_measures(b):
    """Return ({j: scalar RMS}, {j: vector RMS}, at the floor) of the base fit, nT."""
    floor = b.floor
    scalar_rms, vector_rms = _rms_of(b.ev0, b.data.n_sensors)
    at_floor = (all(v <= AT_FLOOR_RATIO * floor.per_sensor_nt[j - 1]
                    for j, v in scalar_rms.items())
                and all(v <= AT_FLOOR_RATIO * floor.vector_floor_nt(j)
                        for j, v in vector_rms.items()))
    return scalar_rms, vector_rms, at_floor


def _candidate_tokens(b, candidates, propose, found):
    """Return (token, label, sensor) to test: ``candidates``, or the catalog and proposals."""
    if candidates is not None:
        return [(tok, *token_label(tok)) for tok in candidates]
    extra = propose_from_residual(b.data.t, b.ev0.residual) if propose else []
    if propose and found is not None:
        extra += tokens_from_findings(found.to_list())
    return candidate_tokens(b.model, b.data, extra=extra)


def _screen(b, testable, progress):
    """
    Screen every candidate from the base fit; return (trials best first, Screen).

    One Gauss-Newton step each (:meth:`Screen.step`) and its predicted chi-square decrease
    (Rao's score test): above :data:`SCORE_RULE_OUT_BIC` in delta BIC (not under the robust
    loss) the candidate keeps that ('score'), else it is evaluated at the step ('one-step').
    """
    trials, screen = [], None
    if testable:
        # under the robust loss the (least-squares) step is taken on the inliers
        n = b.data.n_samples
        keep = (np.arange(n) if b.loss is None else np.flatnonzero(
            np.all(np.abs(b.ev0.residual / b.sigma[:, None, None]) < 2 * b.f_scale, axis=(0, 2))))
        screen = Screen(b.model, b.params, b.data.raw[:, keep],
                        [c.subset(keep) for c in b.contexts], b.f[keep], b.sigma, b.priors,
                        b.constrained)
    for i, (tok, label, sensor) in enumerate(testable):
        report_progress(progress, 'screen', i, len(testable), tok)
        m_ext, p_ext, added = extend_model(b.model, b.params, tok, b.contexts)
        p_step, score, reach = screen.step(m_ext, p_ext, added, with_decrease=True)
        trials.append(Trial(token=tok, label=label, sensor=sensor, model=m_ext, p=p_step,
                            added=added, ev=None, score_chi2=b.ev0.chi2 - max(score, 0.0),
                            method='score', start=p_ext,
                            hideable=_hideable(reach, int(added.sum()), b.n_obs)))
    report_progress(progress, 'screen', len(testable), len(testable), '')
    for c in trials:
        if not b.robust and np.isfinite(c.chi2) and b.delta_bic(c) > SCORE_RULE_OUT_BIC:
            continue
        # the step halved while it overshoots; if the whole step did, also the candidate's
        # own part alone (the base held); the lower chi-square of those, else the start
        step, best = c.p - c.start, None
        for k in range(STEP_HALVINGS + 1):
            ev = _at_step(b, c, c.start + step / 2 ** k)
            if ev is not None:
                best = (ev, c.start + step / 2 ** k)
                break
        if best is None or k > 0:
            own = c.start + np.where(c.added, step, 0.0)
            ev = _at_step(b, c, own)
            if ev is not None and (best is None or ev.chi2 < best[0].chi2):
                best = (ev, own)
        if best is None:
            best = (evaluate_residuals(c.model, c.start, b.data, b.f, b.sigma, b.contexts,
                                       loss=b.loss), c.start)
        c.ev, c.p = best
        c.method = 'one-step'
    order_by_evidence(trials, b)
    return trials, screen


def _hideable(reach, k, n_obs):
    """
    Return the RMS per axis (nT) of the largest effect the test misses, inf at any size.

    ``reach``: :meth:`Screen.step`'s (absorbed share mu or None, rows, noise sd nT) per sensor
    group; None when the effect is invisible to every fit (its columns along the field's own
    direction: no record tests it).
    What the base leaves of an effect of RMS a on its rows, mu rows a^2 / sd^2 of chi-square,
    must reach k ln(n_obs) - MIN_DELTA_BIC for the delta-BIC test to see it.
    """
    need = k * math.log(n_obs) - MIN_DELTA_BIC
    return max((math.inf if mu <= 0 else sd * math.sqrt(need / (mu * rows))
                for mu, rows, sd in reach if mu is not None), default=None)


def _at_step(b, c, p):
    """Evaluate candidate ``c`` at ``p`` from the base fit's field; None if it does not descend."""
    with np.errstate(over='ignore', invalid='ignore', divide='ignore'):   # caught below
        ev = evaluate_residuals(c.model, p, b.data, b.f, b.sigma, b.contexts,
                                field0=b.ev0.field, loss=b.loss)
    return ev if np.isfinite(ev.chi2) and ev.chi2 <= b.ev0.chi2 else None


def _refit(b, trials, screen, max_refit, p_thr, progress):
    """
    Refit the best ``max_refit`` screened trials in full (in place); return how many.

    Each from its one-step solution, to :data:`REFIT_MAX_NFEV` iterations; then those the
    cap stopped that pass the likelihood tests go on to :data:`REFIT_MORE_NFEV`.
    """
    n_refit = min(max_refit, len(trials))
    capped = []
    for i, c in enumerate(trials[:n_refit]):
        report_progress(progress, 'refit', i, n_refit, c.token)
        if i > 0 and b.delta_bic(c) > MIN_DELTA_BIC:      # cannot become significant
            break
        init = c.p
        # a lag's time constant: from the best of a grid (each point a linear step)
        start = None if screen is None else screen.lag_start(c.model, c.start, c.added,
                                                             lag_grid(b.data.t))
        if start is not None:
            init = start
        if _refit_one(b, c, init, REFIT_MAX_NFEV):
            capped.append(c)
    report_progress(progress, 'refit', n_refit, n_refit, '')
    order_by_evidence(trials, b)
    more = [c for c in capped if c.method == 'refit' and _passes_lr(b, c, p_thr)]
    for i, c in enumerate(more):
        report_progress(progress, 'refit (continued)', i, len(more), c.token)
        _refit_one(b, c, c.p, REFIT_MORE_NFEV)
    if more:
        report_progress(progress, 'refit (continued)', len(more), len(more), '')
        order_by_evidence(trials, b)
    return n_refit


def _refit_one(b, c, init, max_nfev):
    """Refit trial ``c`` from ``init`` (in place); return whether the cap stopped it."""
    # warm start; the cap keeps a parameter the data do not fix from wandering
    r = fit(b.data, c.model, field_nt=b.f, sigma_nt=b.sigma, init=init,
            check_identifiability=False, on_degenerate='flag', robust=b.robust,
            constrained=b.constrained, extra_priors=b.carried_priors(c.model),
            max_nfev=max_nfev, ftol=REFIT_CHI2_TOL / max(b.ev0.chi2, 1.0),
            covariance=reads_stderr(c.model, c.label),
            **({'f_scale': b.f_scale} if b.robust else {}))
    ev = evaluate_residuals(c.model, r.params, b.data, b.f, b.sigma, b.contexts, loss=b.loss)
    # with priors (constrained) the screen's chi-square is no bar: the refit stands
    if ev.chi2 <= c.chi2 or c.ev is None or b.constrained:
        c.p, c.ev, c.method = r.params, ev, 'refit'
        c.reduces = reduces_to_simpler(c.model, r.params, r.stderr, c.label, b.contexts)
    return r.nfev >= max_nfev and not r.success


def _passes_lr(b, c, p_thr):
    """Return whether p < ``p_thr`` and delta BIC < MIN_DELTA_BIC (the likelihood tests)."""
    p_value = likelihood_ratio(b.ev0.chi2 - c.chi2, c.k, b.n_obs)[0]
    return p_value < p_thr and b.delta_bic(c) < MIN_DELTA_BIC


def _held_out(b, trials, n_refit, folds, cv_method, p_thr, progress, held_out):
    """
    Cross-validate the base model and the refitted candidates that pass the likelihood tests.

    Best first, until one removes MIN_EXPLAINED of the excess (each gets ``cv`` and
    ``share``).  Returns the base model's :func:`cross_validate`, None without a held-out test.
    """
    if not held_out:
        return None
    to_cv = [c for c in trials[:n_refit]
             if c.method == 'refit' and _passes_lr(b, c, p_thr) and not c.reduces]
    if not to_cv and trials:
        to_cv = [trials[0]]           # the best one, for its effect size
    model, f, sigma = b.model, b.f, b.sigma
    report_progress(progress, 'cross-validate', 0, len(to_cv) + 1, ','.join(model.spec()))
    cv0 = cross_validate(b.data, model, b.params, f, sigma, folds, method=cv_method,
                         constrained=b.constrained, extra_priors=b.carried_priors(model))
    for i, c in enumerate(to_cv):
        report_progress(progress, 'cross-validate', i + 1, len(to_cv) + 1, c.token)
        inits = [c.p.copy() for _ in cv0['fold_params']]
        for p_i, pf in zip(inits, cv0['fold_params']):
            p_i[~c.added] = pf
        c.cv = cross_validate(b.data, c.model, c.p, f, sigma, folds, inits,
                              method=cv_method, constrained=b.constrained,
                              extra_priors=b.carried_priors(c.model))
        c.share = explained_share(cv0['rms_nt'] ** 2, c.cv['rms_nt'] ** 2, b.floor.value_nt)
        if c.share >= MIN_EXPLAINED and _passes_lr(b, c, p_thr):
            break       # the best candidate that passes every test: the verdict
    done = 1 + sum(c.cv is not None for c in to_cv)
    report_progress(progress, 'cross-validate', done, done, '')
    return cv0


def _rank(b, trials, cv0, held_out, decided, p_thr):
    """Return every trial as a :class:`Candidate`, significant ones first, then by delta BIC."""
    s = b.data.n_sensors
    ev0 = b.ev0
    out = []
    for c in trials:
        d_chi2 = ev0.chi2 - c.chi2
        p_val, logp, d_bic = likelihood_ratio(d_chi2, c.k, b.n_obs)
        sens = sensors_of(c.sensor, s)
        cv_b = cv_a = None
        if c.cv is not None and cv0 is not None:
            cv_b, cv_a = cv0['rms_nt'], c.cv['rms_nt']
        if held_out:
            share, how = c.share, ('held-out' if c.share is not None else None)
        elif c.ev is None:
            share, how = None, None           # ruled out by the score test, not evaluated
        else:
            ms1 = dof_factor(c.model) * c.ev.mean_square
            share, how = explained_share(b.ms0, ms1, b.floor.value_nt), decided
        sig = bool(p_val < p_thr and d_bic < MIN_DELTA_BIC and share is not None
                   and share >= MIN_EXPLAINED
                   and (c.method == 'refit' or not b.constrained) and not c.reduces)
        out.append(Candidate(
            token=c.token, effect=c.label, sensor=c.sensor, n_params=c.k,
            rms_before_nt=scalar_rms_of(ev0.scalar, sens, ev0.kept),
            rms_after_nt=None if c.ev is None else scalar_rms_of(c.ev.scalar, sens, c.ev.kept),
            vector_rms_before_nt=vector_rms_of(ev0.vector, sens, s, ev0.kept),
            vector_rms_after_nt=(None if c.ev is None else
                                 vector_rms_of(c.ev.vector, sens, s, c.ev.kept)),
            delta_chi2=float(d_chi2), delta_bic=d_bic, p_value=p_val, log10_p_value=logp,
            method=c.method, cv_rms_before_nt=cv_b, cv_rms_after_nt=cv_a,
            significant=sig, params=added_params(c.model, c.p, c.added),
            explained_fraction=share, decided_by=how, note=c.reduces,
            hideable_rms_nt=c.hideable))
    sig = [c for c in out if c.significant]
    rest = [c for c in out if not c.significant]
    for part in (sig, rest):
        _order_runs(part, lambda c: c.delta_bic, lambda c: (c.n_params, '(' in c.effect, c.token))
    return sig + rest


def _verdict(b, ranked, ratio, at_floor, held_out, p_thr):
    """Return (token or None, reason): the best significant candidate, unless at the floor."""
    floor = b.floor
    best = ranked[0] if ranked and ranked[0].significant else None
    if at_floor:
        reason = (f'the residual is at the noise floor (largest ratio '
                  f'{ratio:.2f} <= {AT_FLOOR_RATIO:.2f})')
        if best is not None:
            reason += (f'; {best.token} is significant and removes '
                       f'{best.explained_fraction:.0%} of the small excess ({best.decided_by})')
        return None, reason
    if best is not None:
        held = ('' if best.cv_rms_before_nt is None else
                f', held-out RMS {best.cv_rms_before_nt:.2f} -> {best.cv_rms_after_nt:.2f} nT')
        return best.token, (
            f'delta BIC {best.delta_bic:.0f}, p = 10^{best.log10_p_value:.0f}{held}, '
            f'removes {best.explained_fraction:.0%} of the excess over the floor '
            f'({best.decided_by}), floor {floor.value_nt:.2f} nT')
    # a filtered series' floor is a lower bound (core/data/noise.py)
    floor_word = ('noise floor' if 'filtered' not in floor.status else
                  'lower bound of the noise floor (low-pass-filtered series)')
    if not ranked:
        return None, f'the residual is {ratio:.1f} x the {floor_word} and no effect is testable'
    small = [c for c in ranked if c.p_value < p_thr and c.delta_bic < MIN_DELTA_BIC
             and c.explained_fraction is not None]
    reason = (f'the residual is {ratio:.1f} x the {floor_word} but no candidate explains '
              f'it (p-value, BIC and a share of at least {MIN_EXPLAINED:.0%} of the excess '
              f'{"held-out" if held_out else "in-sample"})')
    if small:
        c = small[0]
        # the rule it missed: the share, or (with a share enough) why it was not taken
        why = (f'removes only {c.explained_fraction:.0%}'
               if c.explained_fraction < MIN_EXPLAINED else
               f'removes {c.explained_fraction:.0%} but reduces to a simpler effect ({c.note})'
               if c.note else
               f'removes {c.explained_fraction:.0%} by the one-step screen but was not '
               'refitted, and the constrained mode judges only refitted terms'
               if b.constrained and c.method != 'refit' else
               f'removes {c.explained_fraction:.0%} but not by the held-out test')
        reason += f'; the best, {c.token}, {why}'
    return None, reason + (': the missing effect is not in the list (write a plug-in effect), '
                           'or the field is not uniform'
                           + (', or there are outliers (try --robust)' if not b.robust else ''))
