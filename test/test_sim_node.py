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
Tests of ``fluxgate_sim``: the ROS-free devices (magcal_ros.sim) and the node over them.

The devices' output is read back here through real pseudo-terminals with pyserial and the
protocol parsers, the path a driver takes. The node (magcal_ros.ros.sim_node) is checked as a
ROS user meets it: in the graph under its namespace, logging to rosout, its settings as
parameters from ``--params-file``, ``-p`` and the command-line options, a clean exit on
SIGINT and SIGTERM.
"""

import argparse
import os
import pathlib
import re
import signal
import sys
import time

from magcal_ros.ros.sim_node import FluxgateSimNode, sim_specs
from magcal_ros.serial import make_parser
from magcal_ros.sim import devices
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ros_helpers import console_script, spin_until
import serial
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]


def settings(tmp_path, *argv):
    return devices.resolve_settings(['--dir', str(tmp_path)] + list(argv))


def read_samples(port, parser, n, timeout=10.0):
    """Read ``n`` samples from an open pyserial port; return them."""
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n:
        assert time.monotonic() < deadline, f'only {len(out)} of {n} samples'
        out += parser.feed(port.read(max(1, port.in_waiting)))
    return out


def test_defaults_are_paper004_section_4_1():
    st = devices.resolve_settings([])
    assert (st.dir, st.prefix, st.sensors, st.rate, st.protocol) == \
        ('/tmp/magcal_sim', 'fluxgate', 4, 100.0, 'ascii')
    assert (st.field_nt, st.noise_nt, st.errors, st.trajectory) == \
        (50000.0, 3.0, 'paper004', 'smooth')
    sim = devices.FluxgateSim(st)
    cfg = sim.sim.config
    assert (cfg.declination_deg, cfg.inclination_deg) == (-7.0, 55.0)


def test_shipped_config_equals_the_defaults():
    loaded = devices.load_config(ROOT / 'config' / 'sim.yaml')
    merged = dict(devices.DEFAULTS)
    merged.update(loaded)
    assert merged == devices.DEFAULTS
    # and it sets every parameter the node declares, to the declared default (the commented
    # arrays excepted: ROS parameter files cannot hold an empty list)
    values = yaml.safe_load((ROOT / 'config' / 'sim.yaml').read_text())[
        '/**/fluxgate_sim']['ros__parameters']
    specs = {s.name: s for s in sim_specs()}
    assert set(values) == set(specs) - {'unplug', 'site_gradient', 'sensor_positions_m',
                                        'truth', 'plugins'}
    for name, value in values.items():
        default = specs[name].default
        if isinstance(default, tuple):          # a ROS array parameter (YAML: a list)
            assert value == list(default), name
        else:
            assert value == default and type(value) is type(default), name


def test_parse_unplug_and_options():
    assert devices.parse_unplug('2:5:1.5') == devices.Unplug(2, 5.0, 1.5, None)
    assert devices.parse_unplug('1:0.5:0:/tmp/x/ttyB') == \
        devices.Unplug(1, 0.5, 0.0, '/tmp/x/ttyB')
    for bad in ('2:5', 'a:1:1', '0:1:1', '1:-1:1', '1:1:nan'):
        with pytest.raises(argparse.ArgumentTypeError, match='--unplug'):
            devices.parse_unplug(bad)
    assert devices.parse_option('scale=1e5') == ('scale', 1e5)
    assert devices.parse_option('columns=x,y,z,temp') == ('columns', 'x,y,z,temp')
    with pytest.raises(argparse.ArgumentTypeError, match='KEY=VALUE'):
        devices.parse_option('scale')


@pytest.mark.parametrize('argv, match', [
    (['--option', 'colums=x'], r"unknown option\(s\) \['colums'\]"),
    (['--sensors', '2', '--unplug', '3:1:1'], 'unplug sensor 3 but only 2 sensors'),
    (['--rate', '0'], 'must be > 0'),
    (['--site-gradient', '1,2'], 'five numbers'),
    (['--truth', 'temperature@2'], 'expected TERM=v1,v2'),
    (['--truth', 'nosuch@2=1,2,3'], "unknown effect 'nosuch'"),
    (['--truth', 'aux:aux_motor_current@2=1,2'], r'3 values expected \(vx, vy, vz\)'),
])
def test_bad_options_exit_with_reason(argv, match, capsys):
    with pytest.raises(SystemExit) as exc:
        devices.resolve_settings(argv)
    assert exc.value.code == 2
    assert re.search(match, capsys.readouterr().err)


@pytest.mark.parametrize('params, match', [
    ({'rate': -5.0}, 'rate: must be a finite number > 0 Hz'),
    ({'protocol': 'nmea'}, "unknown protocol 'nmea'"),
    ({'options': '{colums: x}'}, r"unknown option\(s\) \['colums'\]"),
    ({'sensors': 2, 'unplug': ['3:1:1']}, 'unplug sensor 3 but only 2 sensors'),
    ({'unplug': ['2:5']}, '--unplug expects SENSOR:AT_S:FOR_S'),
    ({'site_gradient': [1.0, 2.0]}, 'five numbers'),
    ({'truth': ['periodic(0.23)@2=1,x']}, 'values must be numbers'),
    ({'aux_topics': ['fan_current']}, "no simulated channel 'fan_current'"),
])
def test_node_refuses_bad_parameters(ros_context, ros_namespace, tmp_path, params, match):
    overrides = [Parameter('dir', value=str(tmp_path))] + [
        Parameter(k, value=v) for k, v in params.items()]
    with pytest.raises(ValueError, match=match):
        FluxgateSimNode(context=ros_context, namespace=ros_namespace,
                        parameter_overrides=overrides)
    assert not os.listdir(tmp_path)               # no device was created


def test_node_settings_are_parameters_and_its_folder_is_per_namespace(
        make_node, ros_node, ros_executor, ros_namespace):
    node = make_node(FluxgateSimNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('rate', value=250.0), Parameter('sensors', value=2),
        Parameter('options', value="{columns: 'x,y,z,temp,time'}"),
        Parameter('site_gradient', value=[300.0, -250.0, 400.0, -150.0, 200.0])])
    # no dir given: the namespace's own folder, where the driver of that namespace looks
    folder = devices.DEFAULT_DIR + '_' + ros_namespace.strip('/')
    assert node.paths == [f'{folder}/fluxgate{j}' for j in (1, 2)]
    assert all(os.path.islink(p) for p in node.paths)
    assert (node.settings.rate, node.settings.sensors) == (250.0, 2)
    assert dict(node.settings.option) == {'columns': 'x,y,z,temp,time'}
    # what ros2 param get / describe show: read-only parameters with their unit
    client = AsyncParameterClient(ros_node, f'{ros_namespace}/fluxgate_sim')
    spin_until(ros_executor, client.services_are_ready, message='parameter services')
    fut = client.get_parameters(['rate', 'sensors'])
    spin_until(ros_executor, fut.done, message='get_parameters')
    values = fut.result().values
    assert (values[0].double_value, values[1].integer_value) == (250.0, 2)
    fut = client.describe_parameters([s.name for s in sim_specs()])
    spin_until(ros_executor, fut.done, message='describe_parameters')
    for desc in fut.result().descriptors:
        assert desc.read_only and desc.description, desc.name
    paths = node.paths
    node.destroy_node()
    assert not any(os.path.lexists(p) for p in paths)   # the links are removed


@pytest.mark.parametrize('protocol, options', [
    ('ascii', {}),
    ('ascii', {'columns': 'time,x,y,z,temp', 'scale': 1e5}),
    ('hmr2300_ascii', {}),
    ('hmr2300_binary', {}),
    ('lemi025', {}),
])
def test_stream_in_every_protocol_is_continuous_and_plausible(tmp_path, protocol, options):
    argv = ['--protocol', protocol, '--rate', '1000', '--seed', '3']
    for k, v in options.items():
        argv += ['--option', f'{k}={v}']
    st = settings(tmp_path, *argv)
    sim = devices.FluxgateSim(st)
    ports = []
    try:
        paths = sim.plug_all()
        assert paths == [str(tmp_path / f'fluxgate{j}') for j in range(1, 5)]
        ports = [serial.Serial(p, 115200, timeout=0.05) for p in paths]
        parsers = [make_parser(protocol, **options) for _ in paths]
        # 0.5 s of simulated time in 25 ticks of 20 ms: chunks, not one write per sample;
        # the reader keeps up tick by tick as a driver does (the pty buffer is ~18 kB)
        received = [[] for _ in ports]
        for k in range(25):
            sim.step(0.02 * (k + 1) - 0.0005)   # samples 20k .. 20k+19 are due
            for port, parser, got in zip(ports, parsers, received):
                got += read_samples(port, parser, 20 * (k + 1) - len(got))
        assert sim.sent == 500
        for parser, got in zip(parsers, received):
            assert len(got) == 500
            b = np.array([s.field_nt for s in got])
            mag = np.linalg.norm(b, axis=1)
            # Table 1 errors change |B| by up to ~2 600 nT (paper 004 4.1), noise 3 nT
            assert np.all(np.abs(mag - 50000) < 4000), mag.min()
            # 1 kHz smooth tumbling: consecutive samples differ by rotation + noise only
            # (< 60 nT: |B| * 2 pi * 3.1 / 60 s / 1000 Hz = 16 nT plus noise and quantum)
            assert np.max(np.abs(np.diff(b, axis=0))) < 60
            assert parser.stats.total_errors == 0
            if protocol in ('ascii', 'lemi025'):
                temps = [s.temp_c for s in got]
                assert all(10 < t < 45 for t in temps)
            if protocol == 'lemi025' or 'time' in str(options.get('columns', '')):
                times = np.array([s.device_time for s in got])
                assert np.allclose(np.diff(times), 1e-3, atol=1e-6)
    finally:
        for p in ports:
            p.close()
        sim.close()
    assert not any(os.path.lexists(p) for p in sim.paths)


def test_unplug_schedule_in_process(tmp_path):
    st = settings(tmp_path, '--unplug', '2:0.1:0.2', '--unplug', '3:0.1:0.1:' +
                  str(tmp_path / 'other3'))
    sim = devices.FluxgateSim(st)
    log = []
    try:
        sim.plug_all()
        sim.step(0.05, log.append)
        assert all(d.plugged for d in sim.devices)
        sim.step(0.12, log.append)
        assert not sim.devices[1].plugged and not sim.devices[2].plugged
        assert not os.path.lexists(tmp_path / 'fluxgate2')
        sim.step(0.21, log.append)
        assert sim.devices[2].plugged and sim.devices[2].path == str(tmp_path / 'other3')
        sim.step(0.31, log.append)
        assert sim.devices[1].plugged and os.path.islink(tmp_path / 'fluxgate2')
        assert sim.devices[0].plug_count == 1 and sim.devices[1].plug_count == 2
        assert [m.split(' at ')[0] for m in log] == [
            'sensor2 unplugged', 'sensor3 unplugged', 'sensor3 replugged', 'sensor2 replugged']
    finally:
        sim.close()


def _rosout(node, box):
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return node.create_subscription(Log, '/rosout', box.append, qos)


BAD_OUTPUT = re.compile(r'Traceback|\[ERROR\]|Failed to publish|context is invalid')


def test_process_is_a_ros_node_that_streams_and_stops_cleanly(
        start_process, ros_node, ros_executor, ros_namespace, tmp_path):
    # as launch runs it: a namespace remap, a parameter file, -p, then plain options
    params = tmp_path / 'p.yaml'
    params.write_text('/**/fluxgate_sim:\n  ros__parameters:\n    rate: 150.0\n'
                      '    seed: 3\n    sensors: 3\n')
    logs = []
    _rosout(ros_node, logs)
    proc = start_process(console_script('fluxgate_sim') + [
        '--ros-args', '-r', f'__ns:={ros_namespace}', '--params-file', params, '-p',
        'seed:=7', '--', '--rate', '200', '--dir', tmp_path / 'dev'],
        name='fluxgate_sim', ready='streaming ascii at 200 Hz')
    name = ros_namespace.strip('/') + '.fluxgate_sim'
    spin_until(ros_executor, lambda: ('fluxgate_sim', ros_namespace) in
               ros_node.get_node_names_and_namespaces(), message='the node in the graph')
    spin_until(ros_executor, lambda: any(m.name == name and 'streaming' in m.msg for m in logs),
               message='its log on /rosout')
    lines = [m.msg for m in logs if m.name == name]
    # three sensors (parameter file), seed 7 (-p over the file), 200 Hz (option over both)
    assert [ln.split(' -> ')[1].split()[0] for ln in lines if ' -> ' in ln] == \
        [str(tmp_path / 'dev' / f'fluxgate{j}') for j in range(1, 4)]
    assert 'streaming ascii at 200 Hz per sensor (trajectory smooth, seed 7)' in lines
    with serial.Serial(str(tmp_path / 'dev' / 'fluxgate3'), 115200, timeout=0.05) as port:
        got = read_samples(port, make_parser('ascii'), 100)
    assert all(45000 < np.linalg.norm(s.field_nt) < 55000 for s in got)
    assert proc.stop() == 0                     # SIGINT: clean exit, links removed
    assert proc.signals_sent == ['SIGINT']
    log = proc.read_log()
    assert 'stopped after' in log and not BAD_OUTPUT.search(log), log
    assert not any(os.path.lexists(tmp_path / 'dev' / f'fluxgate{j}') for j in range(1, 4))


def test_repeated_sigint_exits_cleanly(start_process, tmp_path):
    for cycle in range(4):
        proc = start_process(console_script('fluxgate_sim') + [
            '--dir', tmp_path / 'dev', '--rate', '1000'], name=f'sim_{cycle}',
            ready='streaming')
        time.sleep(0.15 * cycle)            # the signal lands at different points
        proc.popen.send_signal(signal.SIGINT)
        assert proc.wait(10) == 0, proc.read_log()
        assert not BAD_OUTPUT.search(proc.read_log()), proc.read_log()
        assert not os.path.lexists(tmp_path / 'dev' / 'fluxgate1')


def test_process_sigterm_duration_and_bad_input(start_process, tmp_path):
    # four independent processes (own folders), started together: each is checked below
    # as it ends, so none waits for the previous one's start-up
    (tmp_path / 'c').mkdir()
    (tmp_path / 'c' / 'fluxgate1').write_text('not a device')
    # with the shipped parameter file, as the launch file passes it (rcl parses it)
    sim_a = start_process(console_script('fluxgate_sim') + [
        '--dir', tmp_path / 'a', '--ros-args', '--params-file', ROOT / 'config' / 'sim.yaml'],
        name='sim_a')
    sim_b = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'b',
                                                            '--duration', '0.3'], name='sim_b')
    sim_c = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'c'],
                          name='sim_c')
    # a parameter of the wrong type: one line, exit status 2
    sim_d = start_process(console_script('fluxgate_sim') + [
        '--dir', tmp_path / 'd', '--ros-args', '-p', 'rate:=abc'], name='sim_d')
    sim_a.wait_for_log('streaming ascii at 100 Hz', 30.0)
    sim_a.popen.send_signal(signal.SIGTERM)
    assert sim_a.wait(10) == 0
    assert sim_b.wait(30) == 0 and 'stopped after' in sim_b.read_log()
    assert sim_c.wait(30) == 2
    assert 'exists and is not a symlink' in sim_c.read_log()
    assert (tmp_path / 'c' / 'fluxgate1').read_text() == 'not a device'
    assert sim_d.wait(30) == 2
    assert 'fluxgate_sim: bad parameters' in sim_d.read_log(), sim_d.read_log()
    assert 'Traceback' not in sim_d.read_log()


def test_plain_process_without_ros(start_process, tmp_path):
    # python -m magcal_ros.sim: the same devices for scripts on a machine without ROS
    proc = start_process([sys.executable, '-m', 'magcal_ros.sim', '--dir', tmp_path / 'dev',
                          '--sensors', '1'], name='sim_plain', ready='streaming')
    assert os.path.islink(tmp_path / 'dev' / 'fluxgate1')
    assert proc.stop() == 0 and 'stopped after' in proc.read_log()


def _chunks(argv, tmp_path, n):
    """Return readings (S, 601 + n, 3) nT and aux channels: 6 s in one chunk, n of one."""
    sim = devices.FluxgateSim(settings(tmp_path, '--errors', 'none', '--noise-nt', '0',
                                       *argv))
    got = []
    sim.listeners.append(lambda t, data: got.append(data))
    first = 600                         # one chunk of 601 samples, then one sample a step
    for k in range(first, first + n):
        sim.step(k / sim.settings.rate)
    raw = np.concatenate([d.raw for d in got], axis=1)
    aux = {c: np.concatenate([d.aux[c] for d in got]) for c in got[0].aux}
    return raw, aux


def test_hidden_effects_reach_the_readings_chunk_by_chunk(tmp_path):
    """
    ``--truth``: a motor-current coupling and a lag, computed here from the channels.

    Ideal sensors without noise, 6 s in one chunk then one sample per step as the live stream
    writes them: the reading with the truth minus the one without is v (I - I0) for the
    coupling (I0 the mean current of the first minute, the reference the simulator states)
    and -tau dx/dt for the lag, x the readings (and a boxcar offset of the formula grammar
    inside its window): inside a chunk the central difference
    (x_k+1 - x_k-1) / 2h, for a sample alone the one-sided (3 x_k - 4 x_k-1 + x_k-2) / 2h of
    the stream (all a live stream has).
    """
    n = 200
    plain, aux = _chunks([], tmp_path / 'a', n)
    hidden, _ = _chunks(['--truth', 'aux:aux_motor_current@2=15,-10,8',
                         '--truth', 'field_rate@3=0.01,0.02,0.005',
                         '--truth', 'offset(window(6.5, 7.25))@4=30,-20,0'], tmp_path / 'b', n)
    minute = devices.Simulator(devices.SimConfig()).aux_channels(np.arange(6000) / 100.0)
    i0 = minute['aux_motor_current'].mean()
    coupling = (aux['aux_motor_current'] - i0)[:, None] * np.array([15.0, -10.0, 8.0])
    assert np.ptp(aux['aux_motor_current']) > 0          # the current steps at 7 s
    np.testing.assert_allclose(hidden[1] - plain[1], coupling, atol=1e-6)
    tau, h, x = np.array([0.01, 0.02, 0.005]), 0.01, plain[2]
    central = (x[2:601] - x[:599]) / (2 * h)                         # samples 1..599
    one_sided = (3 * x[601:] - 4 * x[600:-1] + x[599:-2]) / (2 * h)  # samples 601..
    assert np.abs(tau * one_sided).max() > 10.0          # nT: a sizeable effect
    np.testing.assert_allclose(hidden[2, 1:600] - x[1:600], -tau * central, atol=1e-6)
    np.testing.assert_allclose(hidden[2, 601:] - x[601:], -tau * one_sided, atol=1e-6)
    np.testing.assert_array_equal(hidden[0], plain[0])
    # a composed term of the formula grammar: a boxcar offset inside [6.5, 7.25] s
    t = np.arange(hidden.shape[1]) / 100.0
    inside = (t >= 6.5) & (t <= 7.25)
    np.testing.assert_allclose(hidden[3] - plain[3], inside[:, None] * [30.0, -20.0, 0.0],
                               atol=1e-6)


def test_node_publishes_the_auxiliary_channels(make_node, ros_node, ros_executor,
                                               ros_namespace, tmp_path):
    """The channels on std_msgs/Float64 topics, at least every aux_period_s of sample time."""
    from std_msgs.msg import Float64
    got = {name: [] for name in ('motor_current', 'pump_current', 'heater_power')}
    for name, values in got.items():
        ros_node.create_subscription(Float64, f'{ros_namespace}/{name}',
                                     lambda msg, v=values: v.append(msg.data), 100)
    make_node(FluxgateSimNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('dir', value=str(tmp_path)), Parameter('aux_period_s', value=0.05)])
    spin_until(ros_executor, lambda: len(got['pump_current']) >= 20, timeout_sec=20,
               message='20 pump_current messages')
    # the simulator's channels: pump 1 +- 0.5 A, motor 0..5 A, heater 0..10 W
    assert all(0.5 <= v <= 1.5 for v in got['pump_current'])
    assert got['motor_current'] and all(0.0 <= v <= 5.0 for v in got['motor_current'])
    assert got['heater_power'] and all(0.0 <= v <= 10.0 for v in got['heater_power'])


def test_node_publishes_the_attitude_as_imu_in_enu(make_node, ros_node, ros_executor,
                                                   ros_namespace, tmp_path):
    """imu_topic: sensor_msgs/Imu, body-to-ENU, the vehicle's: body z within its tilt of up."""
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import Imu
    got = []
    ros_node.create_subscription(Imu, f'{ros_namespace}/imu', got.append, 100)
    make_node(FluxgateSimNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('dir', value=str(tmp_path)), Parameter('trajectory', value='vehicle'),
        Parameter('imu_topic', value='imu'), Parameter('imu_period_s', value=0.05),
        Parameter('tilt_deg', value=10.0)])
    spin_until(ros_executor, lambda: len(got) >= 30, timeout_sec=20,
               message='30 Imu messages')
    q = np.array([[m.orientation.w, m.orientation.x, m.orientation.y, m.orientation.z]
                  for m in got])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)
    up = Rotation.from_quat(q, scalar_first=True).apply([0.0, 0.0, 1.0])
    # roll and pitch within 10 deg: body z within 14.1 deg of the ENU up axis
    assert np.degrees(np.arccos(up[:, 2])).max() < 14.2
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in got])
    assert np.all(np.diff(stamps) > 0)
    # one message per 0.05 s of sample time (100 Hz samples: every 5th)
    assert np.median(np.diff(stamps)) == pytest.approx(0.05, abs=0.02)
    assert got[0].angular_velocity_covariance[0] == -1.0
    assert got[0].orientation_covariance[0] > 0
