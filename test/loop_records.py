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
The user's loop, run as a user runs it (issue 32 item 6), and the records it is run on.

:func:`user_loop`: screen the readings (as ``magcal diagnose`` and ``fit`` do), then up to
``rounds`` times: ``diagnose`` the model, add the verdict's token, ``fit`` the new model
(pipeline.calibrate, the code of ``magcal fit``); stop when the verdict is none.  Each
round's held-out RMS is the diagnosis' own (``cv_rms_nt``, the model's residual on
interleaved time blocks it was not fitted on).

The records are the hand-written cross of test/injection.py (3 nT noise, 5 Hz) with
faults written here: spikes, an effect the grammar cannot express (a cross-axis quadratic
in the field), a mount that wobbles (a time-varying misalignment the grammar writes as
``rotation(sin(f))``) and a known one (a thermal lag).
"""
from dataclasses import dataclass, field

import injection as inj
from magcal_ros.core.data.readings import leave_out_unphysical
from magcal_ros.core.discovery import diagnose
from magcal_ros.pipeline import calibrate
import numpy as np

F = inj.F_NT


def spikes(n=3000, seed=3):
    """Nine one-reading spikes of 200-500 nT on sensor 2 (0.3 % of its readings)."""
    data = inj.make(n, seed=seed)
    rng = np.random.default_rng(seed + 100)
    idx = np.sort(rng.choice(np.arange(20, n - 20), 9, replace=False))
    size = rng.choice([-1.0, 1.0], 9) * rng.uniform(200.0, 500.0, 9)
    data.raw[1, idx, rng.integers(0, 3, 9)] += size
    return data


def cross_quadratic(t, temp, aux, b):
    """Sensor 2's x axis reads 400 nT x (b_y / F)(b_z / F): no term of the grammar has it."""
    return {2: np.stack([400.0 * b[:, 1] * b[:, 2] / F ** 2, 0 * t, 0 * t], 1)}


def wobble(period_s=60.0, amp_deg=0.3, sensor=3):
    """Sensor ``sensor``'s mount turns about its z axis by amp sin(2 pi t / period)."""
    def inject(t, temp, aux, b):
        th = np.radians(amp_deg) * np.sin(2 * np.pi * t / period_s)
        k = inj.sensor_matrix(sensor)
        c, s = np.cos(th), np.sin(th)
        turned = np.stack([c * b[:, 0] - s * b[:, 1], s * b[:, 0] + c * b[:, 1], b[:, 2]], 1)
        return {sensor: (turned - b) @ k.T}
    return inject


RECORDS = {
    'spikes': lambda: spikes(),
    'cross_quadratic': lambda: inj.make(3000, seed=7, inject=cross_quadratic),
    'wobble': lambda: inj.make(3000, seed=7, inject=wobble()),
    'lag': lambda: inj.make(3000, seed=7, inject=inj.lag_fault(90.0, (4.0, -3.0, 2.5), 2)),
}


@dataclass
class Round:
    """One round of the loop: the model diagnosed and what the diagnosis said."""

    model: str
    cv_rms_nt: float | None
    at_floor: bool
    token: str | None
    reason: str
    fit_warnings: list = field(default_factory=list)
    refused: str | None = None
    diagnosis: object = field(default=None, repr=False)


def user_loop(data, rounds=4, model='base'):
    """Run the loop on ``data`` (module docstring); return (the screened data, [Round])."""
    data, f, _ = leave_out_unphysical(data, F)
    out = []
    for _ in range(rounds + 1):
        d = diagnose(data, model, field_nt=F)
        r = Round(model, d.cv_rms_nt, bool(d.at_floor), d.verdict_token, d.verdict_reason,
                  diagnosis=d)
        out.append(r)
        if d.verdict_token is None or len(out) > rounds:
            break
        model = f'{model},{d.verdict_token}'
        try:
            run = calibrate(data, model, field_nt=F)
        except ValueError as exc:          # what magcal fit answers with exit 2
            r.refused = str(exc)
            break
        r.fit_warnings = list(run.summary['warnings'])
    return data, out
