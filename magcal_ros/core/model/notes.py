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
Structured warnings: a :class:`Note` is its text (a ``str``) with ``kind`` and ``sensor``.

The ``--json`` output and the calibration file's provenance hold :func:`note_dict` of each.
Kinds used by the library:

``missing_effect``  a sensor's residual is well above the noise floor of its data;
``noise_floor``     the floor is not a single white-noise figure (filtered series, ...);
``not_converged``   the optimiser stopped before convergence;
``degenerate``      the data do not determine the model (flagged instead of refused);
``outliers``        sets excluded as garbage, or too many to be garbage;
``input``           the input looks wrong (units, ...);
``readings``        readings no field produces (a pinned, clipped or repeating channel, spikes),
                    left out of the fit (:mod:`magcal_ros.core.data.readings`);
``mounting``        a sensor's axes mirrored, exchanged or turned, recorded as ``axes(...)``
                    (:mod:`magcal_ros.core.model.plausibility`);
``parameters``      fitted values no real sensor has (unit, gain, angle, offset mistakes);
``note``            anything else (a plain string).
"""


class Note(str):
    """A warning text with its ``kind`` and ``sensor`` (1-based, or None for all)."""

    kind: str
    sensor: int | None

    def __new__(cls, text, kind='note', sensor=None):
        obj = super().__new__(cls, text)
        obj.kind = str(kind)
        obj.sensor = None if sensor is None else int(sensor)
        return obj

    def __reduce__(self):
        return (Note, (str(self), self.kind, self.sensor))


def note_dict(w):
    """``{kind, sensor, text}`` of a :class:`Note`, a plain string or such a dict."""
    if isinstance(w, dict):
        return {'kind': str(w.get('kind', 'note')), 'sensor': w.get('sensor'),
                'text': str(w.get('text', ''))}
    return {'kind': getattr(w, 'kind', 'note'), 'sensor': getattr(w, 'sensor', None),
            'text': str(w)}


def format_note(w):
    """One printable line: ``warning [kind]: text``."""
    d = note_dict(w)
    return f"warning [{d['kind']}]: {d['text']}"
