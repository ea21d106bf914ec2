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
Learning in operation (issue 34): keep the calibration right while the vehicle works.

The calibration node feeds a :class:`Learner` with every matched set of raw readings (and
the attitude), runs its refits in a worker thread and installs what it adopts; the window,
persistence and adoption are in docs/design.md, "Learning in operation".  Units: nT, s.

**The statistic.**  The active calibration gives each sensor's scalar residual
r_j = |b_j| - F; for an array the common mode is removed, e_j = r_j - median_{k != j} r_k
(a change of the field cancels, one sensor's stays its own; with one sensor a long field
excursion reads as a change).  With sigma_j the block's per-axis noise floor, e_j has under
the noise the variance v_j = sigma_j^2 + c_m mean_{k != j} sigma_k^2, c_m the variance of
the median of m = S - 1 unit normals.  z_j = (MAD_TO_SD median |e_j|)^2 / v_j is 1 under the
noise and insensitive to spikes; sqrt(z) has sd :data:`Z_SD_UNIT` / sqrt(n), and a block
*exceeds* when some sqrt(z_j) > 1 + ``exceed_sigmas`` x that sd.

**Validation.**  Every ``holdout_every``-th block of ``holdout_block_s`` is held out; on
each, l_b = log(mean over its sets and sensors of r_j^2 / sigma_j^2 + e_j^2 / v_j, active
calibration over proposal) (r too: a proposal cannot trade a common error for a lower e).
A proposal is valid when the mean of l_b over at least three blocks exceeds
``validate_sigmas`` standard errors (blocks: the residual is correlated within one; a log
ratio: a change's residual varies with the heading by orders of magnitude, its ratio less).
"""
from collections import deque
from dataclasses import dataclass, field

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.data.noise import noise_floor
from magcal_ros.core.live.corrector import held_aux
from magcal_ros.core.model.solvers import MAD_TO_SD
import numpy as np

#: states the learner reports (the node's /diagnostics)
TRACKING = 'tracking'
CHANGE = 'change detected'
READY = 'proposal ready'
ADOPTED = 'adopted'
UNDETERMINED = 'not determined by the recent motion'

#: sd of sqrt(z) of n unit-variance residuals times sqrt(n) (sd(med) / med of a half-normal)
Z_SD_UNIT = 1.166


@dataclass
class LearnConfig:
    """Settings of the learning (the node's ``learn_*`` parameters; module docstring)."""

    window_s: float = 120.0             # the recent data a refit sees, s
    window_sets: int = 4000             # most sets the window holds (thinned evenly in time)
    block_s: float = 1.0                # length of the detector's blocks, s
    exceed_sigmas: float = 5.0          # a block exceeds at sqrt(z) this many sds above 1
    persist_s: float = 90.0             # a change lasts this long before it is refitted, s
    persist_fraction: float = 0.8       # share of its blocks exceeding for a persistent change
    clear_blocks: int = 3               # clean blocks in a row that end a transient
    refit_period_s: float = 10.0        # interval of the periodic refits, s
    holdout_block_s: float = 1.0        # length of the validation's interleaved blocks, s
    holdout_every: int = 3              # every this-th block is held out to validate
    validate_sigmas: float = 3.0        # valid: held-out improvement above this many stderrs
    min_sets: int = 200                 # fewest sets a refit takes

    def check(self):
        """Raise ValueError naming the first setting out of its range."""
        for name in ('window_s', 'block_s', 'persist_s', 'refit_period_s',
                     'holdout_block_s', 'exceed_sigmas', 'validate_sigmas'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'learning: {name} must be > 0, got {v!r}')
        if not 0 < self.persist_fraction <= 1:
            raise ValueError('learning: persist_fraction must be in (0, 1]')
        if self.window_sets < 50 or self.holdout_every < 2 or self.clear_blocks < 1:
            raise ValueError('learning: window_sets >= 50, holdout_every >= 2 and '
                             'clear_blocks >= 1 are needed')
        return self


@dataclass
class Proposal:
    """The result of a refit (:meth:`Learner.refit`)."""

    calibration: object     # the Calibration fitted on the window's non-held-out blocks
    doc: dict               # its calibration document, provenance ``learning`` filled
    undetermined: list      # parameter names the recent motion does not determine (held)
    improvement: float      # mean held-out log ratio of the mean squares, active / proposal
    stderr: float           # its standard error over the held-out blocks
    valid: bool             # improvement > validate_sigmas * stderr
    persistent: bool        # fitted on a persistent change (only then ready to adopt)
    t_from: float           # span of the sets fitted, s
    t_to: float
    sets: int               # sets fitted
    #: {'active': (S,), 'proposal': (S,)} RMS of e_j on the held-out sets, nT
    held_out_rms: dict = field(default_factory=dict)


def detector_residual(cal, data, field_nt):
    """
    Return the detector's residual of a calibration on sets: e (S, N) nT, the scalar r (S, N).

    r_j = |b_j| - F, e_j = r_j - median_{k != j} r_k (module docstring; one sensor: e = r) on
    the :class:`Dataset` ``data``, whose temperatures and channels drive the effects.
    """
    s = data.n_sensors
    r = np.stack([np.linalg.norm(cal.correct(j, data.raw[j - 1], data.context(j)), axis=1)
                  for j in range(1, s + 1)]) - field_nt
    if s == 1:
        return r, r
    others = np.stack([np.median(np.delete(r, j, axis=0), axis=0) for j in range(s)])
    return r - others, r


#: the learner keeps the times of this many latest transients and adoptions (memory flat)
KEEP_EVENTS = 100

#: variance of the median of m unit normals (exact for m <= 4; beyond: pi / (2 m))
_MEDIAN_VAR = {1: 1.0, 2: 0.5, 3: 0.4487, 4: 0.3573}


def common_mode_variance(sigma):
    """(S,) variance of e_j under the noise alone, nT^2, from per-axis noise sds (S,) nT."""
    f2 = np.asarray(sigma, float) ** 2
    m = len(f2) - 1
    return f2 + _MEDIAN_VAR.get(m, np.pi / (2 * m)) * (f2.sum() - f2) / m if m else f2


class _Run:
    """Counts of the blocks since a change's onset (flat memory however long it lasts)."""

    def __init__(self):
        self.blocks = 0          # blocks judged since the onset
        self.exceeded = 0
        self.clean = 0           # clean blocks in a row (0: the latest exceeded)

    def add(self, exceed):
        """Count one more block (``exceed``: it exceeded)."""
        self.blocks += 1
        self.exceeded += bool(exceed)
        self.clean = 0 if exceed else self.clean + 1


class Learner:
    """
    The learning of one array (not thread-safe: the node serialises the calls).

    ``aux_names``: auxiliary columns (``aux_<name>``) kept with the sets.
    """

    def __init__(self, n_sensors, config=None, aux_names=()):
        self.config = (config or LearnConfig()).check()
        self.n = int(n_sensors)
        c = self.config.window_sets
        self._t = np.full(c, np.nan)
        self._raw = np.zeros((self.n, c, 3))
        self._temp = np.full((self.n, c), np.nan)
        self._aux = {a: np.full(c, np.nan) for a in aux_names}
        self._att_t = np.full(2 * c, np.nan)
        self._att_q = np.zeros((2 * c, 4))
        self._att_count = 0
        self._count = 0                     # sets kept in the window (ring position)
        self._last_kept = -np.inf
        self._block = []                    # (t, raw (S, 3), temp (S,), aux dict)
        self._floors = []                   # recent blocks' per-axis noise floors (S,)
        self.active = self.field_nt = None
        self._restart(TRACKING)             # state, onset of the change (s), its blocks
        self._by_sensor = np.zeros(self.n)   # blocks since the onset each sensor exceeded
        self.changed = None                 # sensors (1-based) of the change adopted last
        self.last_z = None                  # (S,) z of the latest block
        self.last_block_t = None
        #: (onset, end) s of the latest changes not learned (at most :data:`KEEP_EVENTS`)
        self.transients = deque(maxlen=KEEP_EVENTS)
        self.proposal = None
        #: (t, improvement) of the latest adoptions (at most :data:`KEEP_EVENTS`)
        self.adoptions = deque(maxlen=KEEP_EVENTS)
        self.n_transients = self.n_adoptions = 0
        self._last_refit = -np.inf
        self._data_from = None              # onset of the change adopted last, s
        self.sets_seen = 0

    def set_active(self, cal, field_nt, t=None):
        """Start tracking calibration ``cal`` (magnitude ``field_nt`` nT) from time ``t``."""
        self.active = cal
        self.field_nt = float(field_nt)
        self._restart(TRACKING if t is None or not self.adoptions else ADOPTED)
        self.proposal = None
        if t is not None:
            self._last_refit = float(t)
        else:                               # a calibration from elsewhere: a fresh start
            self._data_from = None
            self.changed = None

    def add_attitude(self, t, q):
        """One attitude (body-to-world unit quaternion (4,) qw, qx, qy, qz) at time ``t`` s."""
        k = self._att_count % len(self._att_t)
        self._att_t[k] = t
        self._att_q[k] = q
        self._att_count += 1

    def add(self, t, raw, temp=None, aux=None):
        """
        Add one matched set: stamp ``t`` s, raw (S, 3) nT, temp (S,) degC, aux {column: value}.

        Returns True when the set closed a block (the state may have changed).
        """
        self.sets_seen += 1
        cfg = self.config
        if t - self._last_kept >= cfg.window_s / cfg.window_sets:
            k = self._count % cfg.window_sets
            self._t[k] = t
            self._raw[:, k] = raw
            self._temp[:, k] = np.nan if temp is None else temp
            for name, arr in self._aux.items():
                arr[k] = (aux or {}).get(name, np.nan)
            self._count += 1
            self._last_kept = t
        if self.active is None:
            return False
        self._block.append((t, raw, temp, aux))
        if t - self._block[0][0] < cfg.block_s:
            return False
        self._judge_block()
        return True

    def _block_data(self, rows):
        t, raw, temps, auxes = zip(*rows)
        temp = (None if any(x is None for x in temps) else
                np.stack([np.asarray(x, float) for x in temps], axis=1))
        aux = {name: np.array([(a or {}).get(name, np.nan) for a in auxes], float)
               for name in self._aux}
        return Dataset(t=np.array(t, float), raw=np.stack([np.asarray(r, float) for r in raw], 1),
                       temp=temp, aux={k: c for k, c in aux.items() if np.isfinite(c).all()})

    def _judge_block(self):
        rows, self._block = self._block, []
        if len(rows) < 14:
            return
        data = self._block_data(rows)
        t_end = float(data.t[-1])
        floor = noise_floor(data.raw)
        if np.all(np.isfinite(floor)):
            self._floors = (self._floors + [floor])[-30:]
        if not self._floors:
            return
        sigma = np.median(np.array(self._floors), axis=0)
        try:
            e, _ = detector_residual(self.active, data, self.field_nt)
        except Exception:        # noqa: B902 -- a driven effect without its signal: no verdict
            return
        v = common_mode_variance(sigma)
        self.last_z = z = (np.median(np.abs(e), axis=1) * MAD_TO_SD) ** 2 / v
        self.last_block_t = t_end
        over = np.sqrt(z) > 1.0 + self.config.exceed_sigmas * Z_SD_UNIT / np.sqrt(e.shape[1])
        if self.state in (TRACKING, ADOPTED) and over.any():
            self._by_sensor[:] = 0
        self._by_sensor += over
        self._step(bool(np.any(over)), float(data.t[0]), t_end)

    def _restart(self, state, onset=None):
        """Enter ``state``, counting the blocks afresh from ``onset`` (s)."""
        self.state, self.onset, self._since = state, onset, _Run()

    def _step(self, exceed, t_start, t_end):
        if self.state in (TRACKING, ADOPTED):
            if exceed:
                self._restart(CHANGE, t_start)
                self._since.add(True)
            return
        if self.state == READY:
            return                         # waiting for its adoption
        self._since.add(exceed)
        if self._since.clean >= self.config.clear_blocks:
            self.transients.append((self.onset, t_end))
            self.n_transients += 1
            self._restart(TRACKING)

    def persistent(self, now):
        """Tell whether the change on has lasted ``persist_s`` and persists (see the module)."""
        cfg, run = self.config, self._since
        return (self.state in (CHANGE, UNDETERMINED) and self.onset is not None and run.blocks > 0
                and now - self.onset >= cfg.persist_s and run.clean == 0
                and run.exceeded >= cfg.persist_fraction * run.blocks)

    def changed_sensors(self):
        """Sensors (1-based tuple) that exceeded in at least half the blocks since the onset."""
        hit = np.flatnonzero(self._by_sensor >= 0.5 * self._since.blocks) + 1
        return tuple(int(j) for j in hit) or tuple(range(1, self.n + 1))

    def refit_due(self, now):
        """Tell whether a refit is due now (periodic, or a change just turned persistent)."""
        if self.active is None or self.state == READY:
            return False
        if self.persistent(now) and (self.proposal is None or not self.proposal.persistent):
            return True
        return now - self._last_refit >= self.config.refit_period_s

    def window(self, since=None):
        """
        Return the window's sets as a Dataset (chronological copies; attitude when it covers).

        ``since`` (s): only the sets from then on.  None when fewer than
        :attr:`LearnConfig.min_sets`.
        """
        cfg = self.config
        n = min(self._count, cfg.window_sets)
        idx = (np.arange(self._count - n, self._count) % cfg.window_sets)
        t = self._t[idx]
        keep = t >= t[-1] - cfg.window_s if n else np.zeros(0, bool)
        if since is not None:
            keep &= t >= since
        idx = idx[keep]
        if len(idx) < cfg.min_sets:
            return None
        temp = self._temp[:, idx]
        data = Dataset(t=self._t[idx].copy(), raw=self._raw[:, idx].copy(),
                       temp=temp.copy() if np.isfinite(temp).all() else None,
                       aux=held_aux(self._aux, idx), meta={'source': 'live (learning window)'})
        m = min(self._att_count, len(self._att_t))
        if m >= 2:
            from magcal_ros.core.geometry.attitude import with_attitude
            try:
                data, _ = with_attitude(data, self._att_t[:m], self._att_q[:m], 'attitude')
            except ValueError:
                pass                        # no overlap: the magnitude-only fit
            if data.n_samples < cfg.min_sets:
                return None
        return data

    def split(self, data):
        """(fit indices, held-out indices) of interleaved blocks of ``holdout_block_s``."""
        cfg = self.config
        block = np.floor((data.t - data.t[0]) / cfg.holdout_block_s).astype(int)
        held = block % cfg.holdout_every == cfg.holdout_every - 1
        return np.flatnonzero(~held), np.flatnonzero(held)

    def refit(self, now, refit_fn):
        """
        Refit the window (since the onset of a persistent change) and validate the result.

        ``now``: time of the call, s.  ``refit_fn(data, active, sensors) -> (calibration,
        doc, undetermined)`` learns the parameters of ``sensors`` (1-based tuple), holds the
        others (:func:`magcal_ros.pipeline.refit_recent`); a ``doc`` whose
        ``provenance.converged`` is false is never valid.  None with too few sets.
        """
        self._last_refit = now
        persistent = self.persistent(now)
        # the block the change was first seen in holds sets of before it: from its end on
        data = self.window(since=self.onset + self.config.block_s if persistent
                           else self._data_from)
        if data is None:
            return None
        fit_idx, held_idx = self.split(data)
        if len(fit_idx) < self.config.min_sets // 2 or len(held_idx) < 20:
            return None
        if persistent:
            sensors = self.changed_sensors()
        else:           # all, or those of the change adopted last that this refines
            sensors = (self._data_from is not None and self.changed) or tuple(range(1, self.n + 1))
        cal, doc, undetermined = refit_fn(data.subset(fit_idx), self.active, sensors)
        improvement, stderr, rms = self._validate(cal, data.subset(held_idx))
        converged = bool(doc.get('provenance', {}).get('converged', True))
        valid = bool(converged and np.isfinite(improvement) and np.isfinite(stderr)
                     and improvement > self.config.validate_sigmas * stderr)
        doc.setdefault('provenance', {})['learning'] = {
            'window_s': [float(data.t[0]), float(data.t[-1])], 'sets': int(len(fit_idx)),
            'held_out_sets': int(len(held_idx)), 'undetermined': list(undetermined),
            'held_out_improvement': float(improvement),
            'held_out_improvement_stderr': float(stderr), 'valid': valid,
            'change_persistent': bool(persistent), 'sensors_learned': list(sensors),
            'held_out_rms_nt': {k: [float(x) for x in v] for k, v in rms.items()}}
        self.proposal = Proposal(cal, doc, list(undetermined), float(improvement),
                                 float(stderr), valid, bool(persistent), float(data.t[0]),
                                 float(data.t[-1]), int(len(fit_idx)), rms)
        if persistent:
            self.state = READY if valid else UNDETERMINED
        elif valid and self._data_from is not None:
            self.state = READY          # refines the change adopted last, on more of its sets
        return self.proposal

    def _validate(self, cal, held):
        """(mean d, its standard error, held-out RMS) of ``cal`` against the active one."""
        sigma = (np.median(np.array(self._floors), axis=0) if self._floors else
                 noise_floor(held.raw))
        v = common_mode_variance(sigma)
        e_act, r_act = detector_residual(self.active, held, self.field_nt)
        e_new, r_new = detector_residual(cal, held, self.field_nt)
        w = 1.0 / (sigma ** 2)[:, None]

        def score(e, r):
            """Per set: the sum of r_j^2 / sigma_j^2, and of e_j^2 / v_j for an array."""
            out = (r ** 2 * w).sum(axis=0)
            return out + (e ** 2 / v[:, None]).sum(axis=0) if held.n_sensors > 1 else out
        a, b = score(e_act, r_act), score(e_new, r_new)
        block = np.floor((held.t - held.t[0]) / self.config.holdout_block_s).astype(int)
        ids = np.unique(block)
        ratios = np.array([np.log(a[block == k].mean() / b[block == k].mean()) for k in ids])
        rms = {'active': np.sqrt(np.mean(e_act ** 2, axis=1)),
               'proposal': np.sqrt(np.mean(e_new ** 2, axis=1))}
        se = ratios.std(ddof=1) / np.sqrt(len(ratios)) if len(ratios) >= 3 else np.nan
        return float(ratios.mean()), float(se), rms

    def adopt(self, now):
        """
        Adopt the ready proposal: it becomes the active calibration; return it (or None).

        Only a ready one: valid, of a persistent change or refining the change adopted last.
        """
        p = self.proposal
        if self.state != READY or p is None:
            return None
        self.adoptions.append((float(now), p.improvement))
        self.n_adoptions += 1
        onset = self.onset
        if p.persistent:
            self.changed = tuple(p.doc['provenance']['learning']['sensors_learned'])
        self.set_active(p.calibration, self.field_nt, now)
        if onset is not None:       # before the change (and its first block): another sensor
            self._data_from = onset + self.config.block_s
        return p                    # set_active made the state ADOPTED

    def status(self):
        """JSON-ready state for /diagnostics: ``state``, ``message`` and values."""
        out = {'state': self.state, 'sets_seen': int(self.sets_seen),
               'window_sets': int(min(self._count, self.config.window_sets)),
               'transients_not_learned': self.n_transients, 'adoptions': self.n_adoptions}
        if self.last_z is not None:
            out['z'] = [round(float(x), 3) for x in self.last_z]
        if self.onset is not None:
            out['change_onset_s'] = float(self.onset)
        p = self.proposal
        if p is not None:
            out.update(proposal_valid=p.valid, proposal_improvement=round(p.improvement, 3),
                       proposal_improvement_stderr=round(p.stderr, 3),
                       undetermined=list(p.undetermined))
        return out


def feed(learner, data, refit_fn, auto_adopt=True, on_adopt=None):
    """
    Feed a recording to ``learner`` set by set, as the node does (offline runs, tests, bench).

    ``learner`` has its active calibration set; ``data`` a Dataset; ``refit_fn`` as for
    :meth:`Learner.refit`, run when due; with ``auto_adopt`` a ready proposal is adopted at
    once, then ``on_adopt(t, proposal)`` called.  Returns the events [(time s, what,
    detail)]: ``state`` on each change, ``refit`` and ``adopted`` with the :class:`Proposal`.
    """
    events, state = [], learner.state
    att, temp, aux_names = data.attitude, data.temp, list(data.aux or {})
    for k in range(data.n_samples):
        t = float(data.t[k])
        if att is not None:
            learner.add_attitude(t, att[k])
        aux = {a: float(data.aux[a][k]) for a in aux_names} if aux_names else None
        if not learner.add(t, data.raw[:, k], None if temp is None else temp[:, k], aux):
            continue
        if learner.state != state:
            state = learner.state
            events.append((t, 'state', state))
        if learner.refit_due(t):
            p = learner.refit(t, refit_fn)
            if p is not None:
                events.append((t, 'refit', p))
        if learner.state == READY and auto_adopt:
            p = learner.adopt(t)
            events.append((t, 'adopted', p))
            if on_adopt is not None:
                on_adopt(t, p)
        if learner.state != state:
            state = learner.state
            events.append((t, 'state', state))
    return events
