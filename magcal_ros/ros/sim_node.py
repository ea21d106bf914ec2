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
``fluxgate_sim``: the simulated fluxgates of :mod:`magcal_ros.sim` as a ROS 2 node.

A thin node over :class:`magcal_ros.sim.devices.FluxgateSim`: its settings are read-only
parameters (``config/sim.yaml``), overridden by the options of
:func:`magcal_ros.sim.devices.build_parser` (``--config FILE``: a parameter file read before
those of ``--ros-args``). The devices are where the driver of the same namespace looks
(docs/design.md §3). A thread writes the samples each tick; SIGINT/SIGTERM (exit 0) or
``duration`` stops it and removes the links.
"""

import argparse
import functools
import json
import sys
import threading

from magcal_ros.core.data.simulate import attitude_enu
from magcal_ros.ros import params as prm
from magcal_ros.ros.conversions import attitude_msg
from magcal_ros.ros.run import DEFAULT_NAMESPACE, spin_node
from magcal_ros.serial import PROTOCOLS
from magcal_ros.sim import devices
import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu
from std_msgs.msg import Float64

NODE_NAME = devices.NODE_NAME
#: orientation uncertainty stated on the simulated Imu messages (the truth: an AHRS's
#: order of magnitude, for a consumer that weighs the attitude), rad
IMU_SD_RAD = 0.01


def sim_specs():
    """Return the parameters of ``fluxgate_sim`` (all read-only: set at start-up)."""
    d = devices.DEFAULTS
    spec = functools.partial(prm.ParamSpec, read_only=True)
    return [
        spec('dir', '', "folder of the device links <dir>/<prefix>{j}; '' = the namespace's: "
             f'{devices.DEFAULT_DIR} in {devices.DEFAULT_NAMESPACE}, {devices.DEFAULT_DIR}_<ns> '
             'in another; no unit'),
        spec('prefix', d['prefix'], 'link name prefix, sensor j is <dir>/<prefix>j; no unit'),
        spec('sensors', d['sensors'], 'number of simulated sensors; count',
             limits=(1, devices.MAX_SENSORS)),
        spec('sensor_positions_m', (), 'x y z of each sensor in the array frame, flat (3 x '
             'sensors values), m; empty: paper 004 cross of 0.5 m for 4 sensors, the origin '
             'otherwise', item_type=float),
        spec('smooth_period_s', d['smooth_period_s'], 'period of the smooth tumbling '
             '(trajectory smooth covers the sphere in about one), s', limits=(0.1, 1.0e6)),
        spec('rate', d['rate'], 'samples per second per sensor, Hz', prm.positive('Hz')),
        spec('tick', d['tick'], 'write period (samples are written in chunks), s',
             prm.positive('s')),
        spec('protocol', d['protocol'], f'serial protocol, one of {sorted(PROTOCOLS)}; no unit'),
        spec('options', '', 'protocol options as a YAML mapping, e.g. "{columns: '
             '\'x,y,z,temp,time\'}" (scale nT per device unit)'),
        spec('seed', d['seed'], 'random seed; no unit'),
        spec('trajectory', d['trajectory'], 'attitude trajectory (random, smooth, turntable, '
             'cone, vehicle); no unit'),
        spec('field_nt', d['field_nt'], 'total field (at the array centre), nT',
             prm.positive('nT')),
        spec('noise_nt', d['noise_nt'], 'white noise sd per axis, nT', limits=(0.0, 1.0e6)),
        spec('errors', d['errors'], 'sensor errors: paper004 (Table 1) or none; no unit'),
        spec('duration', 0.0, 'stop after this time, s (0: run until SIGINT)',
             limits=(0.0, 1.0e9)),
        spec('unplug', (), "faults 'SENSOR:AT_S:FOR_S[:NEW_PATH]' (times in s), e.g. "
             "['2:10:1.5']"),
        spec('truth', (), "hidden effects 'EFFECT=V1,V2,...' as magcal simulate --truth "
             "(values in the units of the effect's parameters), e.g. "
             "['aux:aux_motor_current@2=15,-10,8']"),
        spec('plugins', (), 'effect plug-in modules imported before the truth is read, as '
             'magcal --plugin; no unit'),
        spec('aux_topics', tuple(d['aux_topics']), 'std_msgs/Float64 topics publishing the '
             'simulated auxiliary channels (motor_current: A, pump_current: A, heater_power: '
             'W), see aux_period_s; the names the calibration and corrector nodes take in '
             'aux_topics'),
        spec('aux_period_s', 0.0, 'longest interval between two messages of an auxiliary '
             'channel, s of sample time (0: one message per sample, what keeps a busy '
             'subscriber taking them in step with the raw fields; a jump of more than 2 % is '
             'published at once)', limits=(0.0, 1.0e6)),
        spec('imu_topic', d['imu_topic'], 'sensor_msgs/Imu topic publishing the true attitude '
             'of the array (orientation body-to-world, world ENU, REP 103/145: the calibration '
             "node's imu_topic); '' for none"),
        spec('imu_period_s', d['imu_period_s'], 'interval between two Imu messages, s of sample '
             'time (one per sample when shorter than the sample period)',
             limits=(1.0e-6, 1.0e6)),
        spec('tilt_deg', d['tilt_deg'], 'largest roll and pitch of the vehicle trajectory, deg',
             limits=(0.0, 90.0)),
        spec('site_gradient', (), 'constant site gradient [GXX, GXY, GXZ, GYY, GYZ] in the '
             'world (NED) frame, nT/m; empty: a uniform field', item_type=float),
    ]


class FluxgateSimNode(Node):
    """The ``fluxgate_sim`` node; ValueError for bad settings or a path that is not a link."""

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)
        super().__init__(NODE_NAME, **kwargs)
        given = {name: prm.value(self, name) for name in prm.declare(self, sim_specs())}
        settings = dict(devices.DEFAULTS, dir=devices.device_dir(self.get_namespace()))
        settings.update(devices.settings_from_parameters(given, 'parameters'))
        devices.check_settings(settings)
        self.settings = argparse.Namespace(**settings)
        self.sim = devices.FluxgateSim(self.settings)
        self._stop = threading.Event()
        #: set when the stream ended by itself (``duration``): the spin loop then ends
        self.finished = threading.Event()
        try:
            self.sim.plug_all()
        except Exception:
            self.sim.close()
            raise
        for line in devices.describe_start(self.sim, self.settings):
            self.get_logger().info(line)
        # the auxiliary channels, as a real vehicle's nodes would publish them
        self._aux_pubs = {'aux_' + name: self.create_publisher(Float64, name, 10)
                          for name in self.settings.aux_topics}
        self._aux_last = {}                 # column -> (sample time s, value) last published
        if self._aux_pubs:
            self.sim.listeners.append(self._publish_aux)
        self._imu_pub = None
        self._imu_next = 0.0                # sample time of the next Imu message, s
        if self.settings.imu_topic:
            self._imu_pub = self.create_publisher(Imu, self.settings.imu_topic, 50)
            self.sim.listeners.append(self._publish_imu)
        self._thread = threading.Thread(target=self._stream, name='fluxgate_sim', daemon=True)
        self._thread.start()

    @property
    def paths(self):
        """Link paths of the simulated devices, sensor 1 first."""
        return list(self.sim.paths)

    def _publish_aux(self, t, data):
        # one message per sample by default (a busy subscriber stays in step with the raw
        # fields); aux_period_s > 0 thins them, every jump published at once
        period = self.settings.aux_period_s
        for column, pub in self._aux_pubs.items():
            for tk, value in zip(t, data.aux[column]):
                t_last, v_last = self._aux_last.get(column, (-np.inf, np.nan))
                if (tk - t_last >= period or not abs(value - v_last)
                        <= 0.02 * max(1.0, abs(v_last))):
                    pub.publish(Float64(data=float(value)))
                    self._aux_last[column] = (tk, value)

    def _publish_imu(self, t, data):
        # the true attitude as an AHRS gives it: body-to-world ENU, stamped on the node's clock
        if data.attitude is None or not len(t):
            return
        now = self.get_clock().now().nanoseconds * 1e-9
        for k in range(len(t)):
            if t[k] + 1e-9 < self._imu_next:
                continue
            self._imu_next = t[k] + self.settings.imu_period_s
            q = attitude_enu(data.attitude[k:k + 1])[0]
            self._imu_pub.publish(attitude_msg(q, stamp=now - (t[-1] - t[k]),
                                               frame_id='magcal_array',
                                               sd_rad=IMU_SD_RAD))

    def _stream(self):
        try:
            log = self.get_logger()
            devices.stream(self.sim, self.settings, log.info, self._stop, log.warning)
        finally:
            self.finished.set()

    def destroy_node(self):
        """Stop the stream, remove the links, then destroy the node."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.sim.close()
        self.get_logger().info(devices.describe_stop(self.sim))
        return super().destroy_node()


def split_command_line(argv):
    """
    Separate this program's own options from ``--ros-args ... [--]`` sections.

    Returns (own: the options of :func:`magcal_ros.sim.devices.build_parser`, ros:
    the ``--ros-args`` sections in order, for rclpy), lists of str.
    """
    own, ros, in_ros = [], [], False
    for a in argv:
        in_ros = in_ros or a == '--ros-args'
        (ros if in_ros else own).append(a)
        in_ros = in_ros and a != '--'
    return own, ros


def _list_of(kind):
    return lambda values: [kind(v) for v in values]


#: an option's value as its parameter's (the others are taken as they are)
_AS_PARAMETER = {
    'option': lambda v: json.dumps(dict(v)) if v else '',
    'unplug': lambda v: [
        f'{u.sensor}:{u.at_s}:{u.for_s}' + (f':{u.new_path}' if u.new_path else '') for u in v],
    'site_gradient': _list_of(float), 'sensor_positions_m': _list_of(float),
    'truth': _list_of(str), 'plugins': _list_of(str), 'dir': str}


def overrides_from_options(args):
    """ROS parameter overrides for the options given on the command line (parsed ``args``)."""
    return [Parameter('options' if key == 'option' else key,
                      value=_AS_PARAMETER.get(key, lambda v: v)(value))
            for key, value in devices.options_given(args).items()]


def main(args=None):
    """Console script ``fluxgate_sim``; ``args`` as ``sys.argv[1:]`` (may hold --ros-args)."""
    argv = list(sys.argv[1:] if args is None else args)
    own, ros = split_command_line(argv)
    parser = devices.build_parser()
    options = parser.parse_args(own)               # exit 2 with one line when malformed
    if options.config:
        # read before the --ros-args files and -p, which therefore override it
        ros = ['--ros-args', '--params-file', options.config, '--'] + ros
    node_cls = functools.partial(FluxgateSimNode,
                                 parameter_overrides=overrides_from_options(options))
    return spin_node(node_cls, NODE_NAME, [sys.argv[0]] + ros)


if __name__ == '__main__':
    sys.exit(main())
