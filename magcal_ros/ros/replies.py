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
The calibration node's Trigger replies: a short summary, a newline, then one JSON object.

``ros2 service call`` prints the message on one line: the first line is what a user reads.
"""
import json

#: longest first line of a service reply
HEADLINE = 100


def reply(response, success, summary, payload):
    """
    Fill a Trigger response: a short first line, more lines, newline, one JSON object.

    A long first line is broken after its lead (``not calibrated: <reason>`` becomes
    ``not calibrated:`` and the reason on the next line).
    """
    first, _, rest = summary.strip().partition('\n')
    lead, sep, reason = first.partition(': ')
    if len(first) > HEADLINE and sep:
        first = lead + ':\n' + reason
    summary = first + ('\n' + rest if rest else '')
    response.success = bool(success)
    response.message = summary + '\n' + json.dumps(payload, sort_keys=False)
    return response
