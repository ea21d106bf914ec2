"""Tests of ``fluxgate_sim`` (magcal_ros.ros.sim_node): settings, streaming, faults.

The simulator is a plain process without rclpy; its output is read back here through real
pseudo-terminals with pyserial and the protocol parsers, the path a driver takes.
"""

import argparse
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

from magcal_ros.ros import sim_node
from magcal_ros.serial import make_parser
import numpy as np
import pytest
from ros_helpers import console_script, subprocess_env
import serial

ROOT = pathlib.Path(__file__).resolve().parents[1]


def settings(tmp_path, *argv):
    return sim_node.resolve_settings(['--dir', str(tmp_path)] + list(argv))


def read_samples(port, parser, n, timeout=10.0):
    """Read ``n`` samples from an open pyserial port; return them."""
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n:
        assert time.monotonic() < deadline, f'only {len(out)} of {n} samples'
        out += parser.feed(port.read(max(1, port.in_waiting)))
    return out


def test_defaults_are_paper004_section_4_1():
    st = sim_node.resolve_settings([])
    assert (st.dir, st.prefix, st.sensors, st.rate, st.protocol) == \
        ('/tmp/magcal_sim', 'fluxgate', 4, 100.0, 'ascii')
    assert (st.field_nt, st.noise_nt, st.errors, st.trajectory) == \
        (50000.0, 3.0, 'paper004', 'smooth')
    sim = sim_node.FluxgateSim(st)
    cfg = sim.sim.config
    assert (cfg.declination_deg, cfg.inclination_deg) == (-7.0, 55.0)


def test_shipped_config_equals_the_defaults():
    loaded = sim_node.load_config(ROOT / 'config' / 'sim.yaml')
    merged = dict(sim_node.DEFAULTS)
    merged.update(loaded)
    assert merged == sim_node.DEFAULTS


def test_parse_unplug_and_options():
    assert sim_node.parse_unplug('2:5:1.5') == sim_node.Unplug(2, 5.0, 1.5, None)
    assert sim_node.parse_unplug('1:0.5:0:/tmp/x/ttyB') == \
        sim_node.Unplug(1, 0.5, 0.0, '/tmp/x/ttyB')
    for bad in ('2:5', 'a:1:1', '0:1:1', '1:-1:1', '1:1:nan'):
        with pytest.raises(argparse.ArgumentTypeError, match='--unplug'):
            sim_node.parse_unplug(bad)
    assert sim_node.parse_option('scale=1e5') == ('scale', 1e5)
    assert sim_node.parse_option('columns=x,y,z,temp') == ('columns', 'x,y,z,temp')
    with pytest.raises(argparse.ArgumentTypeError, match='KEY=VALUE'):
        sim_node.parse_option('scale')


def test_ros_args_from_launch_are_understood(tmp_path):
    # launch_ros runs: fluxgate_sim --ros-args -r __ns:=/magcal --params-file sim.yaml
    yaml_file = tmp_path / 'p.yaml'
    yaml_file.write_text('/**/fluxgate_sim:\n  ros__parameters:\n    rate: 250.0\n'
                         "    options: {columns: 'x,y,z,temp,time'}\n")
    st = sim_node.resolve_settings(['--ros-args', '-r', '__ns:=/magcal', '--params-file',
                                    str(yaml_file), '-p', 'seed:=7', '--', '--sensors', '2'])
    assert (st.rate, st.seed, st.sensors) == (250.0, 7, 2)
    assert dict(st.option) == {'columns': 'x,y,z,temp,time'}


@pytest.mark.parametrize('argv, match', [
    (['--ros-args', '-p', 'rate:=-5.0'], 'rate must be a number > 0'),
    (['--ros-args', '-p', 'sensors:=9'], 'sensors must be 1..4'),
    (['--ros-args', '-p', 'bogus:=1'], "unknown fluxgate_sim setting 'bogus'"),
    (['--option', 'colums=x'], r"unknown option\(s\) \['colums'\]"),
    (['--sensors', '2', '--unplug', '3:1:1'], 'unplug sensor 3 but only 2 sensors'),
    (['--rate', '0'], 'must be > 0'),
])
def test_bad_settings_exit_with_reason(argv, match, capsys):
    with pytest.raises(SystemExit) as exc:
        sim_node.resolve_settings(argv)
    assert exc.value.code == 2
    assert re.search(match, capsys.readouterr().err)


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
    sim = sim_node.FluxgateSim(st)
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
    sim = sim_node.FluxgateSim(st)
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


def test_process_prints_paths_streams_and_stops_cleanly(start_process, tmp_path):
    proc = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'dev',
                                                           '--rate', '200'],
                         name='fluxgate_sim', ready='streaming ascii at 200 Hz')
    lines = proc.read_log().splitlines()
    assert [ln.split(' -> ')[1].split()[0] for ln in lines[:4]] == \
        [str(tmp_path / 'dev' / f'fluxgate{j}') for j in range(1, 5)]
    with serial.Serial(str(tmp_path / 'dev' / 'fluxgate4'), 115200, timeout=0.05) as port:
        got = read_samples(port, make_parser('ascii'), 100)
    assert all(45000 < np.linalg.norm(s.field_nt) < 55000 for s in got)
    assert proc.stop() == 0                     # SIGINT: clean exit, links removed
    assert proc.signals_sent == ['SIGINT']
    assert 'stopped after' in proc.read_log()
    assert not any(os.path.lexists(tmp_path / 'dev' / f'fluxgate{j}') for j in range(1, 5))


def test_process_sigterm_duration_and_bad_link_path(start_process, tmp_path):
    proc = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'a'],
                         name='sim_a', ready='streaming')
    proc.popen.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
    proc = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'b',
                                                           '--duration', '0.3'], name='sim_b')
    assert proc.wait(30) == 0 and 'stopped after' in proc.read_log()
    (tmp_path / 'c').mkdir()
    (tmp_path / 'c' / 'fluxgate1').write_text('not a device')
    proc = start_process(console_script('fluxgate_sim') + ['--dir', tmp_path / 'c'],
                         name='sim_c')
    assert proc.wait(30) == 2
    assert 'exists and is not a symlink' in proc.read_log()
    assert (tmp_path / 'c' / 'fluxgate1').read_text() == 'not a device'


def test_sim_node_imports_no_rclpy():
    code = ('import sys, magcal_ros.ros.sim_node; '
            "bad = [m for m in sys.modules if m.split('.')[0] == 'rclpy' "
            "or m.split('.')[0].endswith('_msgs')]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60, env=subprocess_env())
    assert res.returncode == 0, res.stdout + res.stderr
