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
The profiled (variable-projection) maximum-likelihood problem of a magnetometer array.

The residuals are r_jk = (raw_jk - f_j(p, B_k)) / sigma_j (:meth:`Model.forward`), |B_k| =
F_k; for given p each B_k is profiled by Gauss-Newton steps on the sphere and the Jacobian is
projected, J = (I - G (G^T G)^-1 G^T) dr/dp with G_k = -dr_k/d(delta_1, delta_2) (3G x 2 per
epoch), so that J^T J is the Fisher information of p with the fields unknown (variable
projection, Golub & Pereyra 1973, Kaufman 1975: docs/papers.md).
"""
import numpy as np


def tangent_basis(u):
    """(e1, e2), each (N, 3): a right-handed basis (e1, e2, u) at each unit vector of u (N, 3)."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(u, e1)


def inverse_2x2(a, b, c, d):
    """Return the entries (00, 01, 10, 11), each (N,), of the inverses of [[a, b], [c, d]]."""
    det = a * d - b * c
    return d / det, -b / det, -c / det, a / det


def prior_information(priors, cols, p):
    """
    Return what prior rows add to the normal equations of the parameters ``cols`` (K,).

    ``priors`` [(index into ``p`` (P,), mean, sd)], others ignored.  Returns ((K,) 1 / sd^2
    added to the diagonal of J^T J, (K,) (p_i - mean) / sd^2 added to J^T r).
    """
    pos = {int(c): k for k, c in enumerate(cols)}
    lam, grad = np.zeros(len(cols)), np.zeros(len(cols))
    for i, mean, sd in priors:
        if i in pos:
            lam[pos[i]] += 1.0 / sd ** 2
            grad[pos[i]] += (p[i] - mean) / sd ** 2
    return lam, grad


class ProfiledProblem:
    """
    Normalised residuals and projected Jacobian of the ML problem of one group of sensors.

    The unknown x (P_g,) holds the group's sensors' parameters, then the array-wide ones
    (:attr:`cols`, indices into p); the rest of p is held at ``p_full`` (default
    ``model.default_params()``).  Evaluations are cached on x.

    ``model`` prepared on ``contexts`` (S,); ``data_raw`` (S, N, 3) nT; ``f_nt`` (N,) |B_k|
    nT; ``sensors`` 1-based; ``sigma`` (S,) nT; ``priors`` [(index, mean, sd)] appended as
    (p_i - mean) / sd; ``robust``: the field profiled with the soft-L1 IRLS weights (scale
    ``f_scale``); ``field0`` (N, 3) nT: a nearby field, one Gauss-Newton step from it.
    A reading a ``drop`` term leaves out has zero rows and does not inform its set's field
    (a set without any kept reading is profiled from all).
    """

    def __init__(self, model, data_raw, contexts, f_nt, sensors, sigma, priors=(),
                 robust=False, f_scale=3.0, p_full=None, field0=None):
        self.model, self.raw, self.ctx, self.f = model, data_raw, contexts, f_nt
        self.sensors, self.sigma = list(sensors), sigma
        self.robust, self.f_scale = robust, f_scale
        self.cols = np.concatenate([np.arange(model.n_params)[model.sensor_slices[j - 1]]
                                    for j in self.sensors] + [model.array_cols]).astype(int)
        self.priors = list(priors)
        self._cache_key = None
        self.p_full = model.default_params() if p_full is None else np.array(p_full, float)
        self.field0 = field0
        self._aid_setup()
        self._drop_setup()

    def _drop_setup(self):
        """Set keep (N, G (+1)) 0/1 per member (None: all) and field_w, the field's weights."""
        self.keep = self.field_w = None
        if not self.model.drops or not self.ctx:
            return
        mask = self.model.reading_mask(self.ctx[0].t)
        m = mask[np.array(self.sensors) - 1].T
        if self.aid is not None:
            m = np.concatenate([m, mask.any(axis=0)[:, None]], axis=1)
        if m.all():
            return
        self.keep = m.astype(float)
        self.field_w = np.where(m.any(axis=1, keepdims=True), self.keep, 1.0)

    def _aid_setup(self):
        """Set up the attitude's observation of the field: a member after the sensors."""
        from magcal_ros.core.effects.attitude_ref import attitude_reference
        found = attitude_reference(self.model)
        rot = self.ctx[0].attitude if self.ctx else None
        self.aid = None
        if found is None or rot is None:
            return
        (self.aid, self.aid_slice), self.rot = found, rot
        arr = list(self.model.array_cols)
        sl = self.aid_slice
        #: positions of the attitude's parameters among the array-wide columns
        self.aid_arr = np.array([arr.index(i) for i in range(sl.start, sl.stop)], int)
        self.aid_proj = None        # the projector at the last evaluation

    @property
    def aid_sigma(self):
        """Return the attitude observation's sd, nT (1 deg of the field until estimated)."""
        s = self.aid.sigma_nt
        return s if np.isfinite(s) and s > 0 else float(np.mean(self.f)) * np.radians(1.0)

    @property
    def n_members(self):
        """Rows of 3 per epoch: the group's sensors, and the attitude when it observes."""
        return len(self.sensors) + (self.aid is not None)

    def _sensor_residual(self, j, p, b, mats, adds):
        """(N, 3) sensor j's normalised residual (raw - forward) / sigma_j at the field b."""
        return (self.raw[j - 1] - self.model.forward(j, p, b, self.ctx[j - 1], mats[j],
                                                     adds[j])) / self.sigma[j - 1]

    def _aid_residual(self, p, b):
        """(N, 3) the attitude's normalised residual proj (y - B) / sigma_a."""
        proj, y = self.aid.observation(p[self.aid_slice], self.rot, self.f)
        self.aid_proj = proj
        return np.einsum('nij,nj->ni', proj, y - b) / self.aid_sigma

    @property
    def member_counts(self):
        """(G,) or (G + 1,) int: the sets each member (sensor, attitude) has rows in."""
        if self.keep is None:
            return np.full(self.n_members, self.raw.shape[1])
        return self.keep.sum(axis=0).astype(int)

    @property
    def n_observations(self):
        """Return the observations net of the field: the sum over sets with rows of rows - 2."""
        g = len(self.sensors)
        aid = self.aid.rank if self.aid is not None else 0
        if self.keep is None:
            return int((3 * g + aid - 2) * self.raw.shape[1])
        rows = 3 * self.keep[:, :g].sum(axis=1) + (aid * self.keep[:, g] if aid else 0)
        return int(np.sum(np.where(rows > 0, rows - 2, 0)))

    def full(self, x):
        """(P,) :attr:`p_full` with the group's entries ``cols`` replaced by x (P_g,)."""
        p = self.p_full.copy()
        p[self.cols] = x
        return p

    def _field(self, p):
        """Return (field (N, 3) nT, {j: A_j}, {j: additive (N, 3) nT or None}): GN on |B| = F."""
        n = self.raw.shape[1]
        mats = {j: self.model.matrix(j, p) for j in self.sensors}
        adds = {j: self.model.fixed_additive(j, p, self.ctx[j - 1], n) for j in self.sensors}
        if self.field0 is not None:
            b, steps = self.field0, 1
        else:
            cor = np.stack([self.model.correct(j, p, self.raw[j - 1], self.ctx[j - 1])
                            for j in self.sensors])
            fw = None if self.field_w is None else self.field_w[:, :len(self.sensors)]
            if self.robust and len(self.sensors) > 2:
                # one spiking sensor cannot pull the field
                acc = (np.median(cor, axis=0) if fw is None else
                       np.nanmedian(np.where(fw.T[:, :, None] > 0, cor, np.nan), axis=0))
            else:
                wts = 1.0 / self.sigma[np.array(self.sensors) - 1] ** 2
                acc = (np.einsum('gnc,g->nc', cor, wts) if fw is None
                       else np.einsum('gnc,ng,g->nc', cor, fw, wts))
            b, steps = acc / np.linalg.norm(acc, axis=1, keepdims=True) * self.f[:, None], 2
        # -dr_j/d delta_a = F A_j e_a / sigma_j: the 2 x 2 normal equations are quadratic forms
        # of M_j = A_j^T A_j / sigma_j^2 (of their sum with equal weights), the right-hand
        # sides projections of s = sum_j A_j^T r_j / sigma_j
        per_sensor = self.robust or self.field_w is not None
        a_sig = {j: mats[j] / self.sigma[j - 1] for j in self.sensors}
        m_j = {j: a_sig[j].T @ a_sig[j] for j in self.sensors}
        m_sum = sum(m_j.values())
        f2 = self.f * self.f

        def forms(x1, y1, x2, y2):
            # (3, N): the rows' dot products (x1.y1, x1.y2, x2.y2) of the tangent forms
            pairs = ((x1, y1), (x1, y2), (x2, y2))
            return np.stack([np.einsum('ij,ij->i', x, y) for x, y in pairs])
        for _ in range(steps):
            e1, e2 = tangent_basis(b / self.f[:, None])
            h = np.zeros((3, n))
            s = np.zeros((n, 3))
            for gi, j in enumerate(self.sensors):
                r = self._sensor_residual(j, p, b, mats, adds)
                if per_sensor:
                    w = np.ones(n) if self.field_w is None else self.field_w[:, gi]
                    if self.robust:
                        w = w / np.sqrt(1.0 + np.sum(r * r, axis=1) / self.f_scale ** 2)
                    h += w * forms(e1 @ m_j[j], e1, e2 @ m_j[j], e2)
                    r = r * w[:, None]
                s += r @ a_sig[j]
            if not per_sensor:
                h = forms(e1 @ m_sum, e1, e2 @ m_sum, e2)
            if self.aid is not None:
                # the attitude's rows: -dr/d delta_a = F proj e_a / sigma_a
                r = self._aid_residual(p, b)
                w = (1.0 / np.sqrt(1.0 + np.sum(r * r, axis=1) / self.f_scale ** 2)
                     if self.robust else np.ones(n))
                if self.field_w is not None:
                    w = w * self.field_w[:, -1]
                p1 = np.einsum('nij,nj->ni', self.aid_proj, e1)
                p2 = np.einsum('nij,nj->ni', self.aid_proj, e2)
                h = h + w * forms(p1, p1, p2, p2) / self.aid_sigma ** 2
                s = s + r * (w / self.aid_sigma)[:, None]
            # the 2 x 2 systems component by component (faster than batched matmuls, bench/)
            i11, i12, i21, i22 = inverse_2x2(h[0] * f2, h[1] * f2, h[1] * f2, h[2] * f2)
            g1s = self.f * np.einsum('ij,ij->i', e1, s)
            g2s = self.f * np.einsum('ij,ij->i', e2, s)
            d1 = i11 * g1s + i12 * g2s
            d2 = i21 * g1s + i22 * g2s
            b = b + self.f[:, None] * (d1[:, None] * e1 + d2[:, None] * e2)
            b = b / np.linalg.norm(b, axis=1, keepdims=True) * self.f[:, None]
        return b, mats, adds

    def field_columns(self, b, mats):
        """
        Return G (N, 3G, 2) = -dr_k/d(delta_1, delta_2), delta (rad) in the tangent plane.

        At the profiled field ``b`` (N, 3) nT with ``mats`` {sensor: (3, 3) A_j}; rows as the
        residuals' (the attitude's last), zero for the readings left out.
        """
        e1, e2 = tangent_basis(b / self.f[:, None])
        blocks = [np.stack([e1 @ mats[j].T, e2 @ mats[j].T], axis=2)
                  * (self.f[:, None, None] / self.sigma[j - 1]) for j in self.sensors]
        if self.aid is not None:
            e = np.stack([e1, e2], axis=2)                                  # (N, 3, 2)
            blocks.append(self.aid_proj @ e * (self.f[:, None, None] / self.aid_sigma))
        if self.field_w is not None:
            blocks = [blk * self.field_w[:, gi, None, None] for gi, blk in enumerate(blocks)]
        return np.concatenate(blocks, axis=1)

    def project_out_field(self, b, mats, m):
        """Return (N, 3G, K) (I - G (G^T G)^-1 G^T) m of m (N, 3G, K), G :meth:`field_columns`."""
        gb = self.field_columns(b, mats)
        gbt = np.swapaxes(gb, 1, 2)                    # batched matmul, not einsum: 3-5x faster
        g2 = gbt @ gb
        i = inverse_2x2(g2[:, 0, 0], g2[:, 0, 1], g2[:, 1, 0], g2[:, 1, 1])   # not np.linalg
        return m - gb @ (np.stack([np.stack(i[:2], axis=1), np.stack(i[2:], axis=1)], axis=1)
                         @ (gbt @ m))

    def evaluate(self, x):
        """
        Evaluate the model at x (P_g,) with the field profiled (cached on x).

        Returns p (P,), the field (N, 3) nT, {sensor: (3, 3) A_j} and the normalised residuals
        (N, G (+1), 3) (the attitude's last; zero for the readings left out).
        """
        key = x.tobytes()
        if key != self._cache_key:
            p = self.full(x)
            b, mats, adds = self._field(p)
            rows = [self._sensor_residual(j, p, b, mats, adds) for j in self.sensors]
            if self.aid is not None:
                rows.append(self._aid_residual(p, b))
            every = np.stack(rows, axis=1)                          # (N, G (+1), 3)
            res = every if self.keep is None else every * self.keep[:, :, None]
            self._cache, self._every, self._cache_key = (p, b, mats, res), every, key
        return self._cache

    def reading_residuals(self, x):
        """Return (N, G (+1), 3) :meth:`evaluate`'s ``res`` with the readings left out too."""
        self.evaluate(x)
        return self._every

    def residuals(self, x):
        """Return (3 G N + n_priors,) ``res.ravel()`` at x, then each prior's (p_i - mean) / sd."""
        p, _, _, res = self.evaluate(x)
        pr = [(p[i] - m) / s for i, m, s in self.priors]
        return np.concatenate([res.ravel(), pr]) if pr else res.ravel()

    def _raw_columns(self, p, b):
        """
        Return the unprojected columns dr/dx by member, the field held at ``b`` (N, 3) nT.

        Two lists over the members: own (P_j, N, 3) and array-wide (n_arr, N, 3) or None.
        """
        def diff(gi, j, cols):
            block, h = self.model.forward_differences(j, p, b, self.ctx[j - 1], cols)
            block /= -(h * self.sigma[j - 1])[:, None, None]
            if self.keep is not None:
                block *= self.keep[None, :, gi, None]           # a reading left out: no row
            return block

        arr_cols = self.model.array_cols
        own, arr = [], []
        for gi, j in enumerate(self.sensors):
            sl = self.model.sensor_slices[j - 1]
            own.append(diff(gi, j, range(sl.start, sl.stop)))
            arr.append(diff(gi, j, arr_cols) if len(arr_cols) else None)
        if self.aid is not None:
            own.append(np.zeros((0, len(self.f), 3)))
            arr.append(self._aid_columns(p, b))
        return own, arr

    def _aid_columns(self, p, b):
        """(n_arr, N, 3) dr/dx of the attitude's rows in the array-wide columns (step 1e-7 rad)."""
        pa = np.array(p[self.aid_slice], float)
        r0 = self.aid.residual(pa, self.rot, self.f, b)
        out = np.zeros((len(self.model.array_cols), len(self.f), 3))
        h = 1e-7
        for k, col in enumerate(self.aid_arr):
            dp = pa.copy()
            dp[k] += h
            out[col] = (self.aid.residual(dp, self.rot, self.f, b) - r0) / (h * self.aid_sigma)
        if self.keep is not None:
            out *= self.keep[None, :, -1, None]                 # the sets left out: no rows
        return out

    def _prior_jacobian(self):
        """Return (n_priors, P_g): 1 / sd on each prior's parameter column."""
        pr = np.zeros((len(self.priors), len(self.cols)))
        where = {c: k for k, c in enumerate(self.cols)}
        for r, (i, _, s) in enumerate(self.priors):
            pr[r, where[i]] = 1.0 / s
        return pr

    def jacobian(self, x):
        """Return the (3 G N + n_priors, P_g) variable-projection Jacobian of :meth:`residuals`."""
        p, b, mats, res = self.evaluate(x)
        n = res.shape[0]
        own, arr = self._raw_columns(p, b)
        jac = np.zeros((n, self.n_members, 3, len(self.cols)))
        col = 0
        n_arr = len(self.model.array_cols)
        for gi in range(self.n_members):
            jac[:, gi, :, col:col + len(own[gi])] = own[gi].transpose(1, 2, 0)
            col += len(own[gi])
            if n_arr:
                jac[:, gi, :, len(self.cols) - n_arr:] = arr[gi].transpose(1, 2, 0)
        rows = 3 * self.n_members
        jac = self.project_out_field(b, mats, jac.reshape(n, rows, -1))
        jac = jac.reshape(n * rows, -1)
        if self.priors:
            jac = np.vstack([jac, self._prior_jacobian()])
        return jac

    def normal_equations(self, x):
        """
        Return J^T J (P_g, P_g) and J^T r (P_g,) of :meth:`jacobian` at x, block by block.

        With D the unprojected columns and G_k epoch k's field columns,
        J^T J = D^T D - sum_k (G_k^T D_k)^T (G_k^T G_k)^-1 (G_k^T D_k) (J^T r likewise),
        without forming J; the squares loss only (the soft-L1 loss reweights J's rows).
        """
        p, b, mats, res = self.evaluate(x)
        own, arr = self._raw_columns(p, b)
        q = self.field_columns(b, mats)                              # (N, 3G, 2)
        # Gram-Schmidt per epoch, G_k = Q_k L_k^T: the subtracted terms are W^T W and
        # W^T (Q^T r) with W = Q^T D (2 x P_g per epoch)
        q[:, :, 0] /= np.linalg.norm(q[:, :, 0], axis=1, keepdims=True)
        q[:, :, 1] -= np.einsum('ij,ij->i', q[:, :, 0], q[:, :, 1])[:, None] * q[:, :, 0]
        q[:, :, 1] /= np.linalg.norm(q[:, :, 1], axis=1, keepdims=True)
        n_p, n_arr = len(self.cols), len(self.model.array_cols)
        a = np.zeros((n_p, n_p))
        g = np.zeros(n_p)
        # W and Q^T r of each epoch, columns first: (P_g, N) and (N,) per direction
        w = np.zeros((2, n_p, res.shape[0]))
        qtr = np.zeros((2, res.shape[0]))
        sa = slice(n_p - n_arr, n_p)
        col = 0
        for gi, blk in enumerate(own):
            so = slice(col, col + len(blk))
            col = so.stop
            flat = blk.reshape(len(blk), 3 * len(res))               # (P_j, 3N)
            r = np.ascontiguousarray(res[:, gi])                     # (N, 3)
            a[so, so] = flat @ flat.T
            g[so] = flat @ r.ravel()
            qj = q[:, 3 * gi:3 * gi + 3]                             # (N, 3, 2)

            def qt(x, qj=qj):
                # Q^T x per epoch for columns x (K, N, 3): (2, K, N)
                return np.matmul(x.transpose(1, 0, 2), qj).transpose(2, 1, 0)
            w[:, so] = qt(blk)
            qtr += qt(r[None])[:, 0]
            if n_arr:
                fa = arr[gi].reshape(n_arr, -1)                      # (n_arr, 3N)
                a[so, sa] = flat @ fa.T
                a[sa, so] = a[so, sa].T
                a[sa, sa] += fa @ fa.T
                g[sa] += fa @ r.ravel()
                w[:, sa] += qt(arr[gi])
        for d in range(2):
            a -= w[d] @ w[d].T
            g -= w[d] @ qtr[d]
        lam, grad = prior_information(self.priors, self.cols, p)
        a[np.diag_indices_from(a)] += lam
        g += grad
        return a, g
