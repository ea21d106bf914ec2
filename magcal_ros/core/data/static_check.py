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
Check a calibration against static recordings: one |B| everywhere, or why not.

Recordings of a still sensor at different attitudes must give one corrected |B|, the
calibration's reference at the same place and time; when they do not, the pattern says why
(:func:`check_static`'s findings).  Differences are judged against the calibration's own
scalar residual RMS (a direction-dependent error of that size is expected), not the noise.
"""
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

#: |B| differences below this multiple of the calibration's scalar residual RMS agree
AGREE_FACTOR = 3.0
#: field directions closer than this are "the same attitude", deg
SAME_ATTITUDE_DEG = 5.0


@dataclass
class StaticCheck:
    """
    Outcome of :func:`check_static`.

    ``rows`` per recording: ``name``, ``n``, ``b_nt`` mean corrected |B|, ``sd_nt`` its sd,
    ``direction`` (3,) mean unit field direction (sensor's corrected frame) and
    ``minus_reference_nt`` |B| - reference magnitude.
    """

    rows: list
    tolerance_nt: float                 # largest |B| difference that agrees, nT
    #: pairs at the same attitude: names, angle between their fields (deg), |B| difference (nT)
    same_attitude: list = field(default_factory=list)
    findings: list = field(default_factory=list)    # one sentence each
    consistent: bool = True             # one |B| within tolerance_nt, equal to the reference


def check_static(corrected, reference_nt, residual_rms_nt):
    """
    Compare static recordings' corrected |B| with each other and with the reference.

    ``corrected``: {name: (N, 3) corrected field of one static recording, nT};
    ``reference_nt``: the calibration's reference |B|, nT; ``residual_rms_nt``: its scalar
    residual RMS, nT (the tolerance is :data:`AGREE_FACTOR` times it).
    """
    if not corrected:
        raise ValueError('no static recordings to check')
    tol = AGREE_FACTOR * float(residual_rms_nt)
    rows = []
    for name, b in corrected.items():
        b = np.asarray(b, float)
        mag = np.linalg.norm(b, axis=1)
        mean = b.mean(axis=0)
        rows.append({'name': name, 'n': int(len(b)), 'b_nt': float(mag.mean()),
                     'sd_nt': float(mag.std()), 'direction': mean / np.linalg.norm(mean),
                     'minus_reference_nt': float(mag.mean() - reference_nt)})
    same, other = [], []
    for ra, rc in combinations(rows, 2):
        ang = float(np.degrees(np.arccos(np.clip(ra['direction'] @ rc['direction'], -1.0, 1.0))))
        (same if ang < SAME_ATTITUDE_DEG else other).append(
            (ra['name'], rc['name'], ang, rc['b_nt'] - ra['b_nt']))
    out = StaticCheck(rows=rows, tolerance_nt=tol, same_attitude=same)
    changed = set()             # recordings known to see another field than a twin
    for a, c, ang, diff in same:
        if abs(diff) > tol:
            changed.update((a, c))
            out.findings.append(
                f'{a} and {c} see the field from the same attitude ({ang:.1f} deg apart) but '
                f'their |B| differs by {abs(diff):.0f} nT (> {tol:.0f} nT, {AGREE_FACTOR:g} x the '
                "calibration residual): the field at the sensor or the sensor's offset changed "
                'between these recordings (another place, a magnetised object nearby, a power '
                'cycle); no calibration can reconcile them')
    for a, c, ang, diff in other:
        ra = next(r for r in rows if r['name'] == a)
        if abs(diff) <= tol and abs(ra['minus_reference_nt']) > tol:
            out.findings.append(
                f'{a} and {c} lie {ang:.0f} deg apart in attitude yet agree on |B| within '
                f'{abs(diff):.0f} nT: the calibration holds there; their |B| is '
                f"{ra['minus_reference_nt']:+.0f} nT off the calibration's reference "
                f"{reference_nt:.0f} nT, so the field differs from the calibration's "
                '(another place or time)')
    for a, c, ang, diff in other:
        if abs(diff) > tol and (a in changed or c in changed):
            out.findings.append(f'{a} and {c} ({ang:.0f} deg apart in attitude) differ by '
                                f'{abs(diff):.0f} nT, as expected after the change of field '
                                'named above')
        elif abs(diff) > tol:
            out.findings.append(
                f'{a} and {c} ({ang:.0f} deg apart in attitude) differ by {abs(diff):.0f} nT: the '
                'calibration does not hold at these attitudes, or the field changed between the '
                'recordings; the recordings cannot tell which')
    off = [r for r in rows if abs(r['minus_reference_nt']) > tol]
    out.consistent = not out.findings and not off
    if out.consistent:
        out.findings.append(f'all {len(rows)} recordings give |B| within {tol:.0f} nT of the '
                            f'reference {reference_nt:.0f} nT: the calibration is confirmed at '
                            'their attitudes')
    elif off and not out.findings:
        off = [r['minus_reference_nt'] for r in off]
        out.findings.append(f'the recordings agree with each other but their |B| is '
                            f'{min(off):+.0f} to {max(off):+.0f} nT off the reference: the '
                            "field differs from the calibration's")
    return out
