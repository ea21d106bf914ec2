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
Discovery as a search over the model formula (issue 18 item 3).

The drivers a record offers (:mod:`.bases`), with every coupling of the grammar, on every
scope (the sensors the driver explains, alone and as a set; every sensor, each its own and
alike; the array), are

1. **pre-screened** by least squares of each sensor's base residual on the candidate's
   columns (a lower bound of the score statistic), which also gives the scope;
2. **scored** by Rao's score test at the base fit (:class:`.screen.Screen`'s step), the
   best :data:`SCORE_TOP`;
3. **validated held out**: the linearised problem fitted on all folds of interleaved time
   blocks but one, evaluated on that one (:class:`BlockSums`).  A term is adopted if
   significant (Bonferroni over every candidate generated, delta BIC < -10) and it removes
   :data:`~.constants.MIN_EXPLAINED` of the held-out excess over the floor; the largest
   share wins, ties within :data:`TIE_SHARE` to fewer parameters;
4. when no single term brings every sensor to its floor, **pairs** of the best terms.

The adopted term is written in the formula syntax (``offset(s(t, k=8))@2``).
"""
from dataclasses import dataclass, field
import functools
import itertools
import math

from magcal_ros.core.discovery import bases, measures
from magcal_ros.core.discovery.constants import (ALIKE_EXACT_PARAMS, AT_FLOOR_RATIO, CV_TOP,
                                                 LINEAR_MAX_COLUMNS, MAX_LOCALISED_FRACTION,
                                                 MAX_TERM_PARAMS, MIN_DELTA_BIC, MIN_EXPLAINED,
                                                 PAIR_TOP, PRESCREEN_EPOCHS, SCOPE_SHARE,
                                                 SCORE_TOP, SEARCH_BLOCKS_PER_FOLD, SEARCH_FOLDS,
                                                 SPIKE_SHARE, TIE_SHARE)
from magcal_ros.core.discovery.screen import add_gtc, ginv_times
from magcal_ros.core.effects.base import format_arg
from magcal_ros.core.model.fitting import fit_epochs
import numpy as np
from scipy import stats

#: normalisation of the sensor's linear reading in scale/linear/field couplings, nT
LIN_NT = 50000.0


@dataclass
class Term:
    """
    One candidate term: a coupling of a driver on a scope, and its evidence.

    ``coupling``: one of :data:`COUPLINGS` or 'pair' (of the two ``parts``); ``sensors``
    (1-based); ``alike``: one parameter set shared by them; ``k``: parameters added;
    ``approx``: pre-screen chi-square decrease; ``delta_chi2``, ``delta_bic``, ``p_value``:
    the score test; ``share``: held-out share of the excess removed; ``ratios``: {sensor: RMS
    / floor} after the step; ``cv_before``, ``cv_after``: combined held-out RMS, nT.
    """

    coupling: str
    driver: bases.Driver
    sensors: tuple
    alike: bool = False
    k: int = 0
    approx: float = 0.0
    delta_chi2: float | None = None
    delta_bic: float | None = None
    p_value: float | None = None
    share: float | None = None
    ratios: dict | None = None
    cv_before: float | None = None
    cv_after: float | None = None
    parts: tuple = field(default_factory=tuple)

    def text_for(self, n_sensors):
        """Return the formula term, e.g. 'offset(s(t, k=8))@2'."""
        if self.parts:
            return ' + '.join(p.text_for(n_sensors) for p in self.parts)
        body = f'{self.coupling}({self.driver.text})'
        if self.alike and self.coupling != 'field':
            return body + '@alike'
        if self.coupling == 'field' or len(self.sensors) == n_sensors:
            return body
        if len(self.sensors) == 1:
            return f'{body}@{self.sensors[0]}'
        return body + '@{' + ','.join(str(j) for j in self.sensors) + '}'


#: solve a x = b for a PSD a, directions below 1e-9 dropped
solve_psd = functools.partial(measures.solve_psd, rcond=1e-9)


def _proj_ss(x, y):
    """Sum of squares of y (N,) or (N, c) explained by least squares on x (N, m)."""
    xty = x.T @ y
    return float(np.sum(xty * solve_psd(x.T @ x, xty)))


#: for each coupling of the grammar (core/effects/couplings.py), the raw-space pattern of
#: each of its parameters per driver column, to first order: ((axis of dB, axis of lin or
#: None for the driver itself, sign), ...)
_PATTERNS = {
    'offset': [((a, None, 1.0),) for a in range(3)],
    'scale': [((a, a, 1.0),) for a in range(3)],
    'linear': [((a, b, 1.0),) for a in range(3) for b in range(3)],
    # psi: dB_y = x lin_z; varphi: dB_x = x lin_y; theta: dB_x = x lin_z
    'nonorth': [((1, 2, 1.0),), ((0, 1, 1.0),), ((0, 2, 1.0),)],
    # alpha: (lin_y, -lin_x, 0); beta: (0, lin_z, -lin_y); gamma: (-lin_z, 0, lin_x)
    'rotation': [((0, 1, 1.0), (1, 0, -1.0)), ((1, 2, 1.0), (2, 1, -1.0)),
                 ((0, 2, -1.0), (2, 0, 1.0))],
}


def coupling_columns(coupling, x, lin, per_axis=False):
    """
    Raw-space columns (k, N, 3) of a coupling of driver columns x (N, m).

    The first order of core/effects/couplings.py (:data:`_PATTERNS`); field: dB = (X P) lin;
    per axis (rate): dB_i = P_i X_i (offset) or P_i X_i lin_i (scale).  lin (N, 3): the
    sensor's reading / :data:`LIN_NT`.
    """
    n, m = x.shape
    if per_axis:
        out = np.zeros((3, n, 3))
        for a in range(3):
            out[a, :, a] = x[:, a] * (lin[:, a] if coupling == 'scale' else 1.0)
        return out
    if coupling == 'field':
        return x.T[:, :, None] * lin[None, :, :]
    if coupling not in _PATTERNS:
        raise ValueError(f'unknown coupling {coupling!r}')
    patterns = _PATTERNS[coupling]
    out = np.zeros((len(patterns) * m, n, 3))
    for c in range(m):
        for q, pattern in enumerate(patterns):
            for axis, src, sign in pattern:
                out[len(patterns) * c + q, :, axis] += sign * x[:, c] * (
                    1.0 if src is None else lin[:, src])
    return out


def n_params(coupling, m, per_axis=False):
    """Parameters of a coupling of m driver columns, per sensor (field: in all)."""
    return 3 if per_axis else m if coupling == 'field' else len(_PATTERNS[coupling]) * m


class BlockSums:
    """
    The base fit's linearised problem (a :class:`.screen.Screen`) summed per time block.

    For a candidate's raw columns C, [J C]^T P [J C] and [J C]^T P r per block: a fold's fit is
    one solve, its held-out sum of squares r'Pr + 2 s'g + s'M s.
    """

    def __init__(self, screen, sigma, n, folds=SEARCH_FOLDS,
                 blocks_per_fold=SEARCH_BLOCKS_PER_FOLD):
        self.g = screen.groups[0]
        self.sensors = list(self.g['sensors'])
        self.sigma = np.asarray(sigma, float)
        self.n = n
        self.folds = folds
        nb_total = max(folds, min(folds * blocks_per_fold, n // 20))
        self.edges = np.linspace(0, n, nb_total + 1).round().astype(int)
        self.spans = list(zip(self.edges[:-1], self.edges[1:]))
        self.fold_of = np.arange(nb_total) % folds
        g = self.g
        nb = g['jtj'].shape[0]
        self.a = np.zeros((nb_total, nb, nb))
        self.gj = np.zeros((nb_total, nb))
        self.rr = np.zeros(nb_total)
        for gi in range(len(self.sensors)):
            js, r = g['js'][gi], g['r'][gi]
            for b, (e0, e1) in enumerate(self.spans):
                rows = slice(3 * e0, 3 * e1)
                self.a[b] += js[rows].T @ js[rows]
                self.gj[b] += js[rows].T @ r[rows]
                self.rr[b] += float(r[rows] @ r[rows])
        for b, (e0, e1) in enumerate(self.spans):
            self.rr[b] -= float(np.sum(g['rgr'][e0:e1]))
        self.floor_chi2 = None

    def set_floor(self, floor_nt):
        """
        Set the expected r'Pr of each block at the noise floor (S,) nT: tr(P W) per epoch.

        W = diag(floor_j^2 / sigma_j^2); tr(P W) = tr(W) - tr((G^T G)^-1 G^T W G).
        """
        g = self.g
        w = (np.asarray(floor_nt, float) / self.sigma) ** 2
        n = self.n
        # G_j^T G_j per sensor and epoch, (2, 2) of (N,)
        gg = [[[gbj[0][a] * gbj[0][c] + gbj[1][a] * gbj[1][c] + gbj[2][a] * gbj[2][c]
                for c in range(2)] for a in range(2)] for gbj in g['gb']]
        gwg = sum(w[j - 1] * np.array(gg[gi]) for gi, j in enumerate(self.sensors))
        (i00, i01), (i10, i11) = g['ginv']
        tr = i00 * gwg[0, 0] + i01 * gwg[1, 0] + i10 * gwg[0, 1] + i11 * gwg[1, 1]
        per_epoch = 3.0 * float(sum(w[j - 1] for j in self.sensors)) - tr
        self.floor_chi2 = np.array([float(np.sum(per_epoch[a:b])) for a, b in self.spans])
        # per sensor and epoch, the block j of tr(P W P), P = I - G M G^T, M = (G^T G)^-1:
        # 3 w_j - 2 w_j tr(M G_j^T G_j) + tr(M G^T W G M G_j^T G_j)
        mm = [[i00, i01], [i10, i11]]
        mwm = [[sum(mm[a][x] * gwg[x, y] * mm[y][c] for x in range(2) for y in range(2))
                for c in range(2)] for a in range(2)]
        self.floor_epoch = np.zeros((len(self.sensors), n))
        for gi, j in enumerate(self.sensors):
            t1 = sum(mm[a][c] * gg[gi][c][a] for a in range(2) for c in range(2))
            t2 = sum(mwm[a][c] * gg[gi][c][a] for a in range(2) for c in range(2))
            self.floor_epoch[gi] = 3.0 * w[j - 1] - 2.0 * w[j - 1] * t1 + t2

    def candidate(self, cols):
        """
        Per-block sums of a candidate: (B (nb_blk, nb, k), D (nb_blk, k, k), gc (nb_blk, k)).

        ``cols``: list of (sensor j, parameter indices (k_j,), raw columns (k_j, N, 3) nT per
        unit), scaled here by 1/sigma_j.
        """
        g = self.g
        k = 1 + max(int(np.max(idx)) for _, idx, _ in cols)
        # one entry per sensor, so that the products of two parts' columns are formed
        merged = {}
        for j, idx, c in cols:
            merged.setdefault(j, []).append((np.asarray(idx), c))
        cols = [(j, *map(np.concatenate, zip(*parts))) for j, parts in merged.items()]
        n, nbk = self.n, len(self.edges) - 1
        nb = g['jtj'].shape[0]
        bb = np.zeros((nbk, nb, k))
        dd = np.zeros((nbk, k, k))
        gc = np.zeros((nbk, k))
        gtc = np.zeros((2, k, n))
        for j, idx, c in cols:
            gi = self.sensors.index(j)
            cj = c / self.sigma[j - 1]
            js, r = g['js'][gi], g['r'][gi]
            # axis by axis, each with the parameters whose columns touch it
            for a in range(3):
                on = np.flatnonzero(np.any(cj[:, :, a] != 0.0, axis=1))
                if not len(on):
                    continue
                ia, ca = idx[on], cj[on, :, a]
                for b, (e0, e1) in enumerate(self.spans):
                    rows = slice(3 * e0 + a, 3 * e1, 3)
                    fb = ca[:, e0:e1]
                    bb[b][:, ia] += js[rows].T @ fb.T
                    dd[b][np.ix_(ia, ia)] += fb @ fb.T
                    gc[b][ia] += fb @ r[rows]
            add_gtc(gtc, idx, cj, g['gb'][gi])
        m0, m1 = ginv_times(gtc, g)
        for b, (e0, e1) in enumerate(self.spans):
            s = slice(e0, e1)
            dd[b] -= gtc[0][:, s] @ m0[:, s].T + gtc[1][:, s] @ m1[:, s].T
            gc[b] -= gtc[0][:, s] @ g['ginv_gtr'][0][s] + gtc[1][:, s] @ g['ginv_gtr'][1][s]
        return bb, dd, gc

    @staticmethod
    def _system(a, bb, dd, gj, gc):
        m = np.block([[a, bb], [bb.T, dd]])
        return m, np.concatenate([gj, gc])

    def score(self, sums):
        """Predicted chi-square decrease of the candidate on all epochs, and the step."""
        bb, dd, gc = sums
        m, g = self._system(self.a.sum(0), bb.sum(0), dd.sum(0), self.gj.sum(0), gc.sum(0))
        sol = _scaled_solve(m, g)
        return float(-g @ sol), sol

    def held_out(self, sums):
        """Return the held-out sums of squares (chi-square) of the base and the candidate."""
        bb, dd, gc = sums
        ss0 = ss1 = 0.0
        for f in range(self.folds):
            h = self.fold_of == f
            tr = ~h
            a_t, gj_t = self.a[tr].sum(0), self.gj[tr].sum(0)
            a_h, gj_h, rr_h = self.a[h].sum(0), self.gj[h].sum(0), self.rr[h].sum()
            s0 = _scaled_solve(a_t, gj_t)
            ss0 += rr_h + 2 * s0 @ gj_h + s0 @ a_h @ s0
            m_t, g_t = self._system(a_t, bb[tr].sum(0), dd[tr].sum(0), gj_t, gc[tr].sum(0))
            m_h, g_h = self._system(a_h, bb[h].sum(0), dd[h].sum(0), gj_h, gc[h].sum(0))
            s1 = _scaled_solve(m_t, g_t)
            ss1 += rr_h + 2 * s1 @ g_h + s1 @ m_h @ s1
        return float(ss0), max(float(ss1), 0.0)


def _scaled_solve(m, g):
    """Solve m x = -g (PSD m) with m scaled to a unit diagonal."""
    d = np.sqrt(np.clip(np.diag(m), 1e-300, None))
    return solve_psd(m / np.outer(d, d), -g / d) / d


@dataclass
class SearchResult:
    """What the search found: the terms tested (best first) and the adopted one."""

    terms: list
    adopted: Term | None
    n_generated: int
    localised: object = None


def _lin(data):
    return [data.raw[j] / LIN_NT for j in range(data.n_sensors)]


def generate(data, steps=(), windows=(), lines=()):
    """Return the drivers of the record (bases.py) in the order time, channels, products."""
    names = bases.channels_of(data)
    return (bases.time_drivers(data.t, steps, windows, lines)
            + [d for name in names for d in bases.channel_drivers(data, name)]
            + bases.product_drivers(data, names) + [bases.rate_driver(data)])


#: every coupling of the grammar (docs/formulas.md), tried with every driver
COUPLINGS = ('offset', 'scale', 'linear', 'nonorth', 'rotation', 'field')


def couplings_of(driver):
    """
    Couplings tried with a driver: every one of the grammar (issue 32 item 4).

    Per axis (the field rate): offset and scale; ``linear`` up to :data:`LINEAR_MAX_COLUMNS`.
    """
    if driver.per_axis:
        return ('offset', 'scale')
    if driver.x(1).shape[1] > LINEAR_MAX_COLUMNS:
        return tuple(c for c in COUPLINGS if c != 'linear')
    return COUPLINGS


def prescreen(data, resid, sigma, drivers, n_obs, n_eval=PRESCREEN_EPOCHS):
    """
    Rank every (driver, coupling, scope) by a least-squares lower bound of its score.

    ``resid`` (S, N, 3) nT: the base fit's raw-space residual.  Returns a list of Term
    with ``approx`` set (the chi-square decrease scaled to all N epochs), best first.
    """
    s, n = resid.shape[0], resid.shape[1]
    keep = fit_epochs(n, n_eval)
    scale_n = n / len(keep)
    y = [resid[j][keep] / sigma[j] for j in range(s)]
    y_all = np.concatenate([v.ravel() for v in y])
    lin = [x[keep] for x in _lin(data)]
    log_n = math.log(n_obs)
    every = tuple(range(1, s + 1))
    out = []
    for drv in drivers:
        xs = {j: drv.x(j)[keep] for j in range(1, s + 1)}
        # 'linear' first: scale, nonorth and rotation are within its span (their chi-square
        # decrease on a sensor is at most its), so when no sensor could pass the scope rule
        # with linear's decrease they are not formed at all
        lin_top = None
        for cp in sorted(couplings_of(drv), key=lambda c: c != 'linear'):
            m = xs[1].shape[1]
            k = n_params(cp, m, drv.per_axis)
            if (lin_top is not None and cp in ('scale', 'nonorth', 'rotation')
                    and lin_top - k * log_n <= -MIN_DELTA_BIC):
                continue
            if cp == 'field':
                out.append(Term(cp, drv, every, k=k,
                                approx=_joint_ss(cp, k, xs, lin, y_all) * scale_n))
                continue
            if k > MAX_TERM_PARAMS:
                continue
            per = {}
            for j in range(1, s + 1):
                x, yy, ll = xs[j], y[j - 1], lin[j - 1]
                if drv.per_axis:
                    xa = x * ll if cp == 'scale' else x
                    ss = sum(float(xa[:, a] @ yy[:, a]) ** 2 / max(float(xa[:, a] @ xa[:, a]),
                                                                   1e-300) for a in range(3))
                elif cp in ('nonorth', 'rotation'):
                    # the angles couple the axes: one joint least squares of the 3 N values
                    z = coupling_columns(cp, x, ll).reshape(k, -1).T
                    ss = _proj_ss(z, yy.ravel())
                elif cp == 'offset':
                    ss = _proj_ss(x, yy)
                elif cp == 'scale':
                    ss = sum(_proj_ss(x * ll[:, a:a + 1], yy[:, a]) for a in range(3))
                else:
                    ss = sum(_proj_ss(np.concatenate([x * ll[:, b:b + 1] for b in range(3)],
                                                     axis=1), yy[:, a]) for a in range(3))
                per[j] = ss * scale_n
            top = max(per.values())
            if cp == 'linear' and not drv.per_axis:
                lin_top = top
            sig = [j for j in range(1, s + 1) if per[j] - k * log_n > -MIN_DELTA_BIC
                   and per[j] >= SCOPE_SHARE * top]
            for j in sig:
                out.append(Term(cp, drv, (j,), k=k, approx=per[j]))
            if len(sig) >= 2 and k * len(sig) <= MAX_TERM_PARAMS:
                out.append(Term(cp, drv, tuple(sig), k=k * len(sig),
                                approx=sum(per[j] for j in sig)))
            if s > 1 and len(sig) >= 2:
                # every sensor, each its own parameters, and alike (one joint least squares)
                if len(sig) < s and k * s <= MAX_TERM_PARAMS:
                    out.append(Term(cp, drv, every, k=k * s, approx=sum(per.values())))
                if k <= ALIKE_EXACT_PARAMS:
                    approx = _joint_ss(cp, k, xs, lin, y_all, drv.per_axis) * scale_n
                else:
                    approx = sum(per.values())      # an upper bound; the score is exact
                out.append(Term(cp, drv, every, alike=True, k=k, approx=approx))
    out.sort(key=lambda c: -(c.approx - c.k * log_n))
    return out


def _joint_ss(cp, k, xs, lin, y, per_axis=False):
    """Chi-square decrease of one set of ``k`` parameters shared by every sensor of ``xs``."""
    z = np.concatenate([coupling_columns(cp, x, lin[j - 1], per_axis).reshape(k, -1).T
                        for j, x in xs.items()])
    return _proj_ss(z, y)


def term_columns(term, data):
    """Columns of ``term`` for :meth:`BlockSums.candidate`: [(j, idx, C_j)], and k."""
    lin = _lin(data)
    cols, k0 = [], 0
    parts = term.parts or (term,)
    for p in parts:
        kp = n_params(p.coupling, p.driver.x(p.sensors[0]).shape[1], p.driver.per_axis)
        shared = p.alike or p.coupling == 'field'
        for i, j in enumerate(p.sensors):
            c = coupling_columns(p.coupling, p.driver.x(j), lin[j - 1], p.driver.per_axis)
            start = k0 if shared else k0 + i * kp
            cols.append((j, np.arange(start, start + kp), c))
        k0 += kp if shared else kp * len(p.sensors)
    return cols, k0


def _dedupe(terms, n_sensors):
    first = {}
    for t in terms:
        first.setdefault(t.text_for(n_sensors), t)
    return list(first.values())


def search(data, resid, screen, sigma, floor, n_obs, alpha=0.01, steps=(), windows=(), lines=()):
    """
    Search the formula's terms for what the base fit misses (see the module docstring).

    ``data``: the tested epochs (S sensors, N epochs); ``resid`` (S, N, 3): the base fit's
    raw-space residual on them, nT; ``screen``: the base fit's :class:`.screen.Screen` on the
    same epochs; ``sigma`` (S,): its noise levels, nT; ``floor``: the data's NoiseFloor;
    ``n_obs``: observations net of the profiled field (BIC); ``alpha``: family-wise
    significance level (Bonferroni over every candidate generated); ``steps``, ``windows``,
    ``lines``: change points (tuples of s), windows ((t0, t1) s) and spectral lines (Hz).
    Returns a :class:`SearchResult`.
    """
    s, n = resid.shape[0], resid.shape[1]
    drivers = generate(data, steps, windows, lines)
    ranked = prescreen(data, resid, sigma, drivers, n_obs)
    n_gen = max(1, len(ranked))
    p_thr = alpha / n_gen
    log_n = math.log(n_obs)
    sums_all = BlockSums(screen, sigma, n)
    sums_all.set_floor(floor.per_sensor_nt)
    floor_chi2 = float(sums_all.floor_chi2.sum())      # every epoch is held out once
    n_held = float(n)

    def evaluate(term, with_cv):
        cols, k = term_columns(term, data)
        term.k = k
        sm = sums_all.candidate(cols)
        dchi, sol = sums_all.score(sm)
        term.delta_chi2 = dchi
        term.delta_bic = -dchi + k * log_n
        term.p_value = float(stats.chi2.sf(max(dchi, 0.0), k))
        if with_cv:
            ss0, ss1 = sums_all.held_out(sm)
            exc = ss0 - floor_chi2
            term.share = float((ss0 - ss1) / exc) if exc > 0 else 0.0
            term.cv_before = math.sqrt(max(ss0, 0.0) / (3 * s * n_held))
            term.cv_after = math.sqrt(max(ss1, 0.0) / (3 * s * n_held))
            term.ratios = _ratios_after(sums_all, cols, sol, sigma)
        return term

    scored = [evaluate(term, False) for term in _dedupe(ranked, s)[:SCORE_TOP]]
    scored.sort(key=lambda c: c.delta_bic)
    # keep the best lag of each (coupling, scope) only: its time constant is the grid's best
    scored = _dedupe(scored, s)
    good = [c for c in scored if c.p_value < p_thr and c.delta_bic < MIN_DELTA_BIC]
    validated = [evaluate(c, True) for c in good[:CV_TOP]]
    adopt = _choose(validated)
    if adopt is None or max(adopt.ratios.values()) > AT_FLOOR_RATIO:
        singles = [c for c in validated if c.share is not None and c.share > 0][:PAIR_TOP]
        pairs = []
        for a, b in itertools.combinations(singles, 2):
            if a.driver.channel == b.driver.channel and a.coupling == b.coupling and (
                    set(a.sensors) & set(b.sensors)):
                continue            # one driver's bases nest: not two effects
            both = tuple(sorted(set(a.sensors) | set(b.sensors)))
            pairs.append(evaluate(Term('pair', a.driver, both, parts=(a, b)), True))
        pairs = [c for c in pairs if c.p_value < p_thr and c.delta_bic < MIN_DELTA_BIC]
        best_pair = _choose(pairs)
        if best_pair is not None and (adopt is None or best_pair.share > adopt.share + TIE_SHARE):
            validated.append(best_pair)
            adopt = best_pair
    validated.sort(key=lambda c: -(c.share or 0.0))
    rest = [c for c in scored if c not in validated]
    return SearchResult(terms=validated + rest, adopted=adopt, n_generated=n_gen,
                        localised=localised(data.t, sums_all))


def _choose(terms):
    """Return the adoptable term with the largest held-out share; ties to fewer parameters."""
    ok = [c for c in terms if c.share is not None and c.share >= MIN_EXPLAINED]
    if not ok:
        return None
    best = max(c.share for c in ok)
    tied = [c for c in ok if c.share >= best - TIE_SHARE]
    return min(tied, key=lambda c: (c.k, -c.share))


def _ratios_after(sums, cols, sol, sigma):
    """
    {sensor: in-sample residual RMS / floor} after the step ``sol``.

    The sensor's sum of squares over what it holds at the floor (:meth:`BlockSums.set_floor`).
    """
    g = sums.g
    nb = g['jtj'].shape[0]
    sb, sc = sol[:nb], sol[nb:]
    n = sums.n
    u = {}
    for jj, idx, c in cols:
        du = np.tensordot(sc[idx], c, axes=(0, 0)) / sigma[jj - 1]          # (N, 3)
        u[jj] = u.get(jj, 0.0) + du
    # the profiled field takes up the part of the term along the field directions
    gtu = np.zeros((2, n))
    for gi, j in enumerate(sums.sensors):
        if j in u:
            for a in range(2):
                gtu[a] += sum(g['gb'][gi][i][a] * u[j][:, i] for i in range(3))
    mg = ginv_times(gtu, g)
    out = {}
    for gi, j in enumerate(sums.sensors):
        du = u.get(j, np.zeros((n, 3)))
        du = du - np.stack([g['gb'][gi][i][0] * mg[0] + g['gb'][gi][i][1] * mg[1]
                            for i in range(3)], axis=1)
        r = g['r'][gi] + g['js'][gi] @ sb + du.reshape(-1)
        out[j] = math.sqrt(float(r @ r) / float(sums.floor_epoch[gi].sum()))
    return out


@dataclass
class Localized:
    """
    An excess over the floor confined to one interval of time.

    ``t0``, ``t1``: s; ``sensors``: those with 10 % of the excess inside; ``share``: of the
    excess inside; ``ratios_outside``: {sensor: RMS / floor outside}; ``vector``: mostly
    across the field.
    """

    t0: float
    t1: float
    sensors: tuple
    share: float
    ratios_outside: dict
    vector: bool

    @property
    def token(self):
        """Return 'drop(t0, t1)', on the sensors that carry it ('@J', '@{J,K}') unless all."""
        core = f'drop({format_arg(self.t0)}, {format_arg(self.t1)})'
        if not self.sensors or set(self.sensors) >= set(self.ratios_outside):
            return core
        if len(self.sensors) == 1:
            return f'{core}@{self.sensors[0]}'
        return f'{core}@{{{",".join(str(j) for j in sorted(self.sensors))}}}'


def localised(t, sums):
    """
    Describe an excess confined in time, or None (model-free; see :class:`Localized`).

    ``sums``: the base fit's :class:`BlockSums`, its floor set.  The interval of largest
    excess (maximum-sum subarray, Kadane), widened by 0, 1, 2 or 5 % of the record each side,
    is left out of a linearised refit; the first that leaves every sensor within
    :data:`~.constants.AT_FLOOR_RATIO` of its floor, if at most
    :data:`MAX_LOCALISED_FRACTION` of the record and not a few outliers.
    """
    t = np.asarray(t, float)
    g = sums.g
    n, sens = sums.n, sums.sensors
    if n < 100:
        return None
    span = float(t[-1] - t[0])
    fe = sums.floor_epoch
    dt = float(np.median(np.diff(t)))
    nsens = len(sens)

    def refit_outside(out):
        rows = np.repeat(out, 3)
        jtj = sum(g['js'][gi][rows].T @ g['js'][gi][rows] for gi in range(nsens))
        jtr = sum(g['js'][gi][rows].T @ g['r'][gi][rows] for gi in range(nsens))
        return solve_psd(jtj, -jtr)
    step = np.zeros(g['jtj'].shape[0])
    for _ in range(3):
        res = [(g['r'][gi] + g['js'][gi] @ step).reshape(n, 3) for gi in range(nsens)]
        ex_j = np.stack([np.sum(r ** 2, axis=1) for r in res]) - fe      # (S, N) signed
        ex = ex_j.sum(axis=0)
        total = float(ex.sum())
        if total <= 0:
            return None
        # the interval of largest excess above half the mean excess per epoch (Kadane)
        cum = np.concatenate([[0.0], np.cumsum(ex - 0.5 * total / n)])
        low = np.minimum.accumulate(cum)
        i1 = int(np.argmax(cum - low))
        i0 = int(np.argmax(cum[:i1 + 1] == low[i1]))
        if i1 <= i0:
            return None
        for margin in (0.0, 0.01, 0.02, 0.05):
            a = int(np.searchsorted(t, t[i0] - margin * span))
            b = min(n - 1, int(np.searchsorted(t, t[i1 - 1] + margin * span, side='right')) - 1)
            if t[b] - t[a] > MAX_LOCALISED_FRACTION * span:
                return None
            out = np.ones(n, bool)
            out[a:b + 1] = False
            st = refit_outside(out)
            rat = {}
            for gi, j in enumerate(sens):
                r = (g['r'][gi] + g['js'][gi] @ st).reshape(n, 3)[out]
                rat[j] = math.sqrt(float(np.sum(r ** 2)) / float(fe[gi, out].sum()))
            if margin == 0.0:
                step_next = st
            if max(rat.values()) <= AT_FLOOR_RATIO:
                # not a few outliers: its 5 % largest epochs hold at most SPIKE_SHARE
                pos = np.sort(np.clip(ex[a:b + 1], 0.0, None))[::-1]
                if pos[:max(1, len(pos) // 20)].sum() > SPIKE_SHARE * pos.sum():
                    return None
                inside = np.clip(ex_j[:, a:b + 1].sum(axis=1), 0.0, None)
                carry = tuple(int(sens[gi]) for gi in np.flatnonzero(inside >= 0.1 * inside.sum()))
                q = 10.0 ** math.floor(math.log10(dt)) if dt > 0 else 1.0
                return Localized(t0=float(np.floor(t[a] / q) * q),
                                 t1=float(np.ceil(t[b] / q) * q), sensors=carry,
                                 share=float(np.clip(ex[a:b + 1].sum() / total, 0, 1)),
                                 ratios_outside=rat, vector=False)
        step = step_next
    return None
