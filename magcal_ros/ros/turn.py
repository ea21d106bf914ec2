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
The calibration node's turn (docs/design.md §3): :class:`TurnMixin`.

``calibration/turn`` turns a robot in place through ``cmd_vel_topic`` while the node
collects, until sensor 1 has seen ``turn_count`` turns or ``turn_timeout_s`` passed, and
stops it (a zero velocity) after the turn, on an error and on shutdown.
"""
import math
import time

from geometry_msgs.msg import Twist
from magcal_ros.ros import params as prm
from magcal_ros.ros.collection import reply


class TurnMixin:
    """Turn the robot through cmd_vel while collecting (calibration/turn)."""

    async def _on_turn(self, request, response):
        s = prm.calibration_settings(self)
        if self._cmd_vel is None:
            return reply(response, False, 'no cmd_vel_topic: set it (read-only: at start-up) '
                         'to turn the robot', {'state': self._state})
        if not self._busy.acquire(blocking=False):
            return self._reject_busy(response, 'turn')
        try:
            dropped = self._clear('collecting')
            self.get_logger().info(
                f'turning the robot on {s.cmd_vel_topic}: {s.turn_count:g} turns at '
                f'{s.turn_speed_rad_s:g} rad/s (at most {s.turn_timeout_s:g} s)')
            ok, summary, payload = await self._in_worker(self._turn, s)
            payload['sets_dropped'] = dropped
            return reply(response, ok, summary, payload)
        except Exception as exc:         # noqa: B902 -- a service must answer, never die
            self.get_logger().error(f'turn failed: {exc!r}')
            return reply(response, False, f'turn failed: {exc}; the robot is stopped',
                         {'error': str(exc), 'type': type(exc).__name__})
        finally:
            self._stop_robot()
            self._busy.release()

    def _turn(self, s):
        """Drive cmd_vel until the turns are seen or time is up (worker thread)."""
        from magcal_ros.core.geometry.turn import swept_angle
        twist = Twist()
        twist.angular.z = float(s.turn_speed_rad_s)
        want = 2 * math.pi * s.turn_count
        t0 = time.monotonic()
        swept, last_check = 0.0, t0
        try:
            while not self._turn_stop.is_set():
                now = time.monotonic()
                if now - t0 > s.turn_timeout_s:
                    break
                self._cmd_vel.publish(twist)
                if now - last_check >= 0.5:
                    last_check = now
                    n_sets, data, _ = self._snapshot()
                    swept = swept_angle(data.raw[0]) if n_sets else 0.0
                    if swept >= want:
                        break
                self._turn_stop.wait(0.1)
        finally:
            self._stop_robot()
        elapsed = time.monotonic() - t0
        n_sets = self._snapshot()[0]
        payload = {'turns_asked': s.turn_count, 'turns_seen': swept / (2 * math.pi),
                   'elapsed_s': round(elapsed, 2), 'sets': n_sets,
                   'cmd_vel_topic': s.cmd_vel_topic}
        if swept >= want:
            return True, (f'turned {swept / (2 * math.pi):.2f} turns in {elapsed:.1f} s '
                          f'({n_sets} sets collected): the robot is stopped; call '
                          'calibration/calibrate (parameter planar: true for a robot that '
                          'only turns about one axis)'), payload
        why = ('the node is shutting down' if self._turn_stop.is_set() else
               f'turn_timeout_s ({s.turn_timeout_s:g} s) passed')
        return False, (f'turn incomplete: sensor 1 saw {swept / (2 * math.pi):.2f} of '
                       f'{s.turn_count:g} turns when {why}; the robot is stopped (does the '
                       f'base listen on {s.cmd_vel_topic}? wheels slipping?)'), payload

    def _stop_robot(self):
        """Publish a zero velocity on cmd_vel (after a turn, on error, on shutdown)."""
        if self._cmd_vel is not None:
            try:
                self._cmd_vel.publish(Twist())
            except Exception:       # noqa: B902 -- the context may be gone at shutdown
                pass
