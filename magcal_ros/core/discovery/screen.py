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

"""Screening of candidate effects: one Gauss-Newton step of each extended model from the base."""
from magcal_ros.core.discovery.constants import VISIBLE
from magcal_ros.core.discovery.measures import solve_psd
from magcal_ros.core.model.engine import prior_information, ProfiledProblem
from magcal_ros.core.model.fitting import priors_for
import numpy as np


def add_gtc(gtc, cols, cj, gb):
    """Add G^T C per epoch to ``gtc`` (2, K, N) at ``cols``: C ``cj`` (k, N, 3), G ``gb``."""
    for a in range(2):
        gtc[a, cols] += cj[:, :, 0] * gb[0][a] + cj[:, :, 1] * gb[1][a] + cj[:, :, 2] * gb[2][a]


def ginv_times(gtc, g):
    """Return (G^T G)^-1 G^T C, the 2 x 2 inverse applied component by component."""
    (i00, i01), (i10, i11) = g['ginv']
    return gtc[0] * i00 + gtc[1] * i01, gtc[0] * i10 + gtc[1] * i11


def absorbed(ctc, cross, jtj_inv, seen):
    """
    Return the share of a candidate's effect the test sees, in its worst direction.

    The scaled normal equations of base and candidate: ``ctc`` (k, k) C^T P C (P: the field
    projection), ``cross`` (nb, k) J^T C, ``jtj_inv`` (nb, nb) (J^T J)^+; ``seen`` (k, k) C^T
    C, the effect's columns before P, scaled alike.  The least generalised eigenvalue mu of
    the Schur complement S = C^T P C - C^T J (J^T J)^+ J^T C against C^T C: an effect theta
    leaves mu theta^T C^T C theta of its chi-square to the test; the base's own parameters
    (held only by their priors) and the unknown field direction take up the rest; 0: some
    combination is taken whole.  Over the combinations P leaves at least :data:`VISIBLE` of:
    the others no fit of the magnitude sees, whatever the record (None when that is all).
    """
    w, v = np.linalg.eigh(seen)
    keep = w > 1e-12 * max(w.max(), 1e-300)
    half = v[:, keep] / np.sqrt(w[keep])                # (C^T C)^(-1/2) on its range
    nu, u = np.linalg.eigh(half.T @ ctc @ half)
    basis = half @ u[:, nu >= VISIBLE]                  # C^T C-orthonormal, visible
    if not basis.shape[1]:
        return None
    schur = ctc - cross.T @ jtj_inv @ cross
    return float(max(np.linalg.eigvalsh(basis.T @ schur @ basis).min(), 0.0))


class Screen:
    """
    One Gauss-Newton step of an extended model from the base solution, for many candidates.

    The base's variable-projection Jacobian, residual and field projector are formed once;
    a candidate adds its columns C and the step solves the normal equations of [J_base, C]
    (exact to first order for effects that enter linearly).  With P = I - G (G^T G)^-1 G^T
    (G: each epoch's field-direction columns) and P J_base = J_base: J_base^T P C = J_base^T
    C, C^T P C = C^T C - (G^T C)^T (G^T G)^-1 (G^T C), per epoch with 2 x 2 inverses.
    """

    def __init__(self, model, p, raw, contexts, f, sigma, priors=(), constrained=False):
        """
        Form the base fit's scaled normal equations and field projector once.

        ``model``: the base model, prepared; ``p`` (P,) its parameters; ``raw`` (S, N, 3) nT
        and ``contexts``: the screened epochs; ``f`` (N,) nT; ``sigma`` (S,) nT; ``priors``:
        the base fit's (index, mean, sd), and with ``constrained`` each candidate's own, as
        the fit's prior rows (a step keeps what only the priors hold).
        """
        self.model, self.p, self.raw, self.ctx = model, p, raw, contexts
        self.f, self.sigma, self.constrained = f, sigma, constrained
        self.groups = []
        for grp in model.sensor_groups:
            prob = ProfiledProblem(model, raw, contexts, f, grp, sigma, p_full=p)
            x = p[prob.cols]
            r = prob.residuals(x)
            jac = prob.jacobian(x)
            _, b, mats, _ = prob.evaluate(x)
            n, g = len(f), len(grp)
            # (N, 3, 2) field-direction columns of each member (the attitude's too)
            gm = prob.n_members
            g_all = prob.field_columns(b, mats)
            gb = [g_all[:, 3 * gi:3 * gi + 3] for gi in range(gm)]
            gtg = sum(np.swapaxes(x_, 1, 2) @ x_ for x_ in gb)
            a, bb, c, d_ = gtg[:, 0, 0], gtg[:, 0, 1], gtg[:, 1, 0], gtg[:, 1, 1]
            ginv = np.stack([np.stack([d_, -bb], axis=1), np.stack([-c, a], axis=1)],
                            axis=1) / (a * d_ - bb * c)[:, None, None]       # (N, 2, 2)
            r3 = r.reshape(n, gm, 3)
            gtr = sum((np.swapaxes(gb[gi], 1, 2) @ r3[:, gi, :, None])[..., 0]
                      for gi in range(gm))                                    # (N, 2)
            d = np.linalg.norm(jac, axis=0)
            d[d == 0] = 1.0
            js = jac
            js /= d                          # in place: the Jacobian is not needed unscaled
            j4 = js.reshape(n, gm, 3, -1)
            jtj, jtr = js.T @ js, js.T @ r
            lam, grad = prior_information(priors, prob.cols, p)     # scaled as J's columns
            jtj[np.diag_indices_from(jtj)] += lam / d ** 2
            jtr += grad / d
            ginv_gtr = (ginv @ gtr[..., None])[..., 0]                         # (N, 2)
            self.groups.append({
                'sensors': grp, 'cols': prob.cols, 'd': d, 'b': b,
                'jtj': jtj, 'jtr': jtr, 'jtj_inv': np.linalg.pinv(jtj, hermitian=True),
                # per sensor: its rows of the scaled base Jacobian (3N, P), residual (3N,)
                'js': [np.ascontiguousarray(j4[:, gi]).reshape(3 * n, -1) for gi in range(g)],
                'r': [np.ascontiguousarray(r3[:, gi]).reshape(-1) for gi in range(g)],
                # per sensor, axis i and field direction a: the (N,) column G[:, i, a]
                'gb': [[[np.ascontiguousarray(x_[:, i, a]) for a in range(2)]
                        for i in range(3)] for x_ in gb[:g]],
                # (G^T G)^-1 and (G^T G)^-1 G^T r per epoch, component by component (N,)
                'ginv': [[np.ascontiguousarray(ginv[:, a, c]) for c in range(2)]
                         for a in range(2)],
                'ginv_gtr': [np.ascontiguousarray(ginv_gtr[:, a]) for a in range(2)],
                # (G^T r)^T (G^T G)^-1 G^T r per epoch (N,): what no candidate can remove
                'rgr': np.einsum('na,na->n', gtr, ginv_gtr)})
        # base parameter (sensor, effect, name) -> its index in the base model
        self._base_pos = model.param_positions()

    def step(self, m_ext, p_ext, added, with_decrease=False):
        """
        Return (P',) parameters of ``m_ext`` after one Gauss-Newton step from ``p_ext``.

        With ``with_decrease``: (parameters, the chi-square decrease g^T (J^T J)^+ g the
        linearised problem predicts, g = J^T r, the effect's :func:`absorbed` share per sensor
        group as (share, rows, sd of those rows' noise in nT)).
        """
        info = m_ext.param_info()
        new_of_old = np.empty(self.model.n_params, int)
        for i, key in enumerate(info):
            pos = self._base_pos.get(key[:3])
            if pos is not None:
                new_of_old[pos] = i
        p_new = p_ext.copy()
        decrease = 0.0
        reach = []
        own_priors = priors_for(m_ext, {}, True) if self.constrained else ()
        n = len(self.f)
        for g in self.groups:
            grp = g['sensors']
            # sensor 0: a parameter of the whole array (site_gradient), in every sensor's rows
            idx = [i for i in np.flatnonzero(added) if info[i][0] in grp or info[i][0] == 0]
            if not idx:
                continue
            k = len(idx)
            nb = len(g['cols'])
            cross = np.zeros((nb, k))            # J_base^T C
            ctc = np.zeros((k, k))               # C^T C
            ctr = np.zeros(k)                    # C^T r
            rows, noise2 = 0, 0.0                # the effect's rows, their noise variance
            gtc = np.zeros((2, k, n))            # G^T C per epoch, (direction, column, epoch)
            for gi, j in enumerate(grp):
                cols = [c for c, i in enumerate(idx) if info[i][0] in (j, 0)]
                if not cols:
                    continue
                # the candidate's columns of this sensor, (k_j, N, 3), scaled in place
                cj, h = m_ext.forward_differences(j, p_ext, g['b'], self.ctx[j - 1],
                                                  [idx[c] for c in cols])
                cj *= (-1.0 / (h * self.sigma[j - 1]))[:, None, None]
                flat = cj.reshape(len(cols), 3 * n)
                cross[:, cols] += (flat @ g['js'][gi]).T     # as C J: 1.7-1.9x J^T C^T's speed
                ctc[np.ix_(cols, cols)] += flat @ flat.T
                ctr[cols] += flat @ g['r'][gi]
                add_gtc(gtc, cols, cj, g['gb'][gi])
                rows += 3 * n
                noise2 += 3 * n * self.sigma[j - 1] ** 2
            seen = ctc.copy()                    # the effect before the field projection
            # project: subtract the part of C along the field directions of each epoch
            m0, m1 = ginv_times(gtc, g)
            ctc -= gtc[0] @ m0.T + gtc[1] @ m1.T
            ctr -= gtc[0] @ g['ginv_gtr'][0] + gtc[1] @ g['ginv_gtr'][1]
            lam, grad = prior_information(own_priors, idx, p_ext)
            own = ctc.copy()                     # the data's part (not the effect's priors)
            ctc[np.diag_indices_from(ctc)] += lam
            ctr += grad
            dc = np.sqrt(np.clip(np.diag(ctc), 0.0, None))
            dc[dc == 0] = 1.0
            cross_s = cross / dc
            a = np.block([[g['jtj'], cross_s], [cross_s.T, ctc / np.outer(dc, dc)]])
            rhs = -np.concatenate([g['jtr'], ctr / dc])
            sol = solve_psd(a, rhs)
            decrease += float(rhs @ sol)
            if with_decrease:
                scale = np.outer(dc, dc)
                reach.append((absorbed(own / scale, cross_s, g['jtj_inv'], seen / scale), rows,
                              float(np.sqrt(noise2 / rows))))
            p_new[new_of_old[g['cols']]] += sol[:nb] / g['d']
            p_new[idx] += sol[nb:] / dc
        return (p_new, decrease, reach) if with_decrease else p_new

    def lag_start(self, m_ext, p_ext, added, taus):
        """
        Return (P',) a start for the refit of a candidate with lags, or None without a lag.

        One linear :meth:`step` per tau of ``taus`` (s), every lag held at it; the best one.
        """
        tau_idx = [i for i, (_, lab, nm, _) in enumerate(m_ext.param_info())
                   if added[i] and nm == 'tau' and lab.startswith('lag(')]
        if not tau_idx:
            return None
        linear = added.copy()
        linear[tau_idx] = False
        best, best_dec = None, -np.inf
        for tau in taus:
            p0 = p_ext.copy()
            p0[tau_idx] = tau
            p1, dec, _ = self.step(m_ext, p0, linear, with_decrease=True)
            if dec > best_dec:
                best, best_dec = p1, dec
        return best
