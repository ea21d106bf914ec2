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
Effect code that fails: checked once at start-up, contained and named when it runs.

:func:`probe_effect` evaluates an effect at start-up on a context holding only the signals
it declares: reading another (live it is not received), or failing, refuses the plug-in.  At
run time what effect code raises becomes an :class:`EffectError` naming the effect, which the
nodes contain: the sample is not published, the error counted (:class:`EffectErrors`).
"""
from magcal_ros.core.effects.base import Effect, rot_z, SensorContext, SIGNALS
import numpy as np

#: samples of the start-up probe context (2 Hz for 100 s)
PROBE_SAMPLES = 200

#: the SensorContext attribute of each signal (the inverse of effects.SIGNALS, without t)
_ATTRIBUTE_SIGNAL = {attr: name for name, attr in SIGNALS.items() if attr != 't'}


class UndeclaredSignal(Exception):
    """Effect code read a signal its effect does not declare (the probe context only)."""

    def __init__(self, signal):
        super().__init__(signal)
        self.signal = signal


class _DeclaredAux(dict):
    """Auxiliary channels of the probe: reading an absent (undeclared) one raises."""

    def __getitem__(self, key):
        if not dict.__contains__(self, key):
            raise UndeclaredSignal(key)
        return dict.__getitem__(self, key)

    def get(self, key, default=None):
        return self[key]


class DeclaredContext(SensorContext):
    """A :class:`SensorContext` whose undeclared signals raise (``has`` says False, as live)."""

    def __init__(self, declared, **kwargs):
        super().__init__(**kwargs)
        object.__setattr__(self, '_declared', frozenset(declared))
        object.__setattr__(self, 'aux', _DeclaredAux(kwargs.get('aux') or {}))

    def __getattribute__(self, name):
        signal = _ATTRIBUTE_SIGNAL.get(name)
        if signal is not None and signal not in object.__getattribute__(self, '_declared'):
            raise UndeclaredSignal(signal)
        return object.__getattribute__(self, name)

    def has(self, signal):
        """Tell whether ``signal`` is present; False for an undeclared one."""
        if signal != 'time' and signal not in object.__getattribute__(self, '_declared'):
            return False
        return super().has(signal)

    def subset(self, idx):
        """Return the probe context restricted to samples ``idx`` (still guarded)."""
        raw = {k: object.__getattribute__(self, k)
               for k in ('t', 'temp', 'raw_rate', 'attitude')}
        return DeclaredContext(
            object.__getattribute__(self, '_declared'),
            **{k: None if v is None else v[idx] for k, v in raw.items()},
            aux={k: v[idx] for k, v in dict.items(self.aux)})


def probe_context(signals, n=PROBE_SAMPLES):
    """
    Return a :class:`DeclaredContext` with plausible values of exactly ``signals``.

    ``t`` (N,) s; 'temperature' (N,) degC, 'field_rate' (N, 3) nT/s, 'attitude' (N, 3, 3)
    rotations about z, 'aux_<name>' (N,), each only when declared.
    """
    signals = set(signals)
    t = 1000.0 + 0.5 * np.arange(n)
    phase = 2 * np.pi * (t - t[0]) / 37.0
    kwargs = {'t': t, 'aux': {}}
    if 'temperature' in signals:
        kwargs['temp'] = 20.0 + 5.0 * np.sin(phase)
    if 'field_rate' in signals:
        kwargs['raw_rate'] = 300.0 * np.stack([np.cos(phase), np.sin(phase),
                                               0.3 * np.cos(2 * phase)], axis=1)
    if 'attitude' in signals:
        kwargs['attitude'] = rot_z(phase / 3)
    for name in signals:
        if name.startswith('aux_'):
            kwargs['aux'][name] = 2.0 + np.sin(phase + len(name))
    return DeclaredContext(signals | {'time'}, **kwargs)


def probe_effect(cls, ref=None):
    """
    Evaluate the effect class ``cls`` once on a context of its declared signals.

    ``prepare``, ``check``, then ``matrix`` or ``contribution`` (not for an array-wide
    effect), on sensor 2 at its default parameters plus 1e-3 (an effect needing arguments:
    its first ``suggest_args``, if any).  Raises ValueError naming the effect (and ``ref``,
    its plug-in) and the undeclared signal it read, or what its code raised.
    """
    where = f' ({ref})' if ref else ''
    name = getattr(cls, 'name', cls.__name__)
    eff = None
    try:
        if cls.usage is not None:
            # the diagnosis asks suggest_args with the data's signals, whatever they are
            args = list(cls.suggest_args(probe_context(('temperature', 'field_rate',
                                                        'attitude', 'aux_probe'))))
            if not args:
                return
            eff = cls.from_args(args[0], sensor=2)
        else:
            eff = cls(sensor=2)
        ctx = probe_context(eff.signals)
        eff.prepare(ctx)
        eff.check(ctx)
        p = np.asarray(eff.default_params(), float) + 1e-3
        if eff.kind == 'linear':
            eff.matrix(p)
        elif eff.scope == 'sensor':
            lin = np.tile([20000.0, -15000.0, 42000.0], (len(ctx.t), 1))
            out = np.asarray(eff.contribution(p, ctx, lin))
            if out.shape != lin.shape:
                raise ValueError(f'contribution has shape {out.shape}, expected '
                                 f'{lin.shape} (N, 3) nT')
    except UndeclaredSignal as exc:
        declared = ', '.join(repr(s) for s in (eff.signals if eff else ())) or 'none'
        raise ValueError(
            f'effect {name!r}{where} reads the signal {exc.signal!r} but does not declare it '
            f'(signals: {declared}); live that signal is not received for it: add '
            f'{exc.signal!r} to its signals (docs/plugins.md)') from None
    except Exception as exc:                  # noqa: B902 -- any failure of plug-in code
        raise ValueError(f'effect {name!r}{where} fails when evaluated on its declared '
                         f'signals: {type(exc).__name__}: {first_line(exc)}') from None


def first_line(exc):
    """Return the first line of an exception's message (its type's name when empty)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def culprit(exc):
    """Return the token (``label@sensor``) of the innermost effect that raised ``exc``, or None."""
    found = None
    tb = exc.__traceback__
    while tb is not None:
        owner = tb.tb_frame.f_locals.get('self')
        if isinstance(owner, Effect):
            found = owner
        tb = tb.tb_next
    if found is None:
        return None
    return found.label if found.scope == 'array' else f'{found.label}@{found.sensor}'


class EffectError(Exception):
    """
    Effect code raised while a sample was corrected (or a calibration made ready).

    ``effect`` is the token of the effect whose code raised (``temperature@2``), None when
    the traceback passes through no effect; ``error`` what it raised.
    """

    def __init__(self, error, effect=None, where=None):
        self.error = error
        self.effect = culprit(error) if effect is None else effect
        who = f'effect {self.effect}' if self.effect else (where or 'the calibration')
        super().__init__(f'{who} raised {type(error).__name__}: {first_line(error)}')

    @property
    def key(self):
        """Key the error is counted under: the effect's token, else the message."""
        return self.effect or str(self)


class EffectErrors(dict):
    """Errors of effect code seen by a node, counted per effect: key -> [count, first message]."""

    def add(self, err, what=''):
        """Count ``err`` (``what``: what was lost); True for an effect's first error (log it)."""
        entry = self.get(err.key)
        if entry is None:
            self[err.key] = [1, f'{err}' + (f' ({what})' if what else '')]
            return True
        entry[0] += 1
        return False

    def counts(self):
        """{effect token or message: errors counted}."""
        return {k: v[0] for k, v in self.items()}

    def summary(self):
        """One line per effect, joined: '<first error>: N times'."""
        return '; '.join(f'{msg}: {n} time{"s" if n > 1 else ""}' for n, msg in self.values())
