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
rosbag2 recordings of the array -> :class:`~magcal_ros.core.data.dataset.Dataset` (no rclpy).

Reads with the ``rosbags`` library (pure Python; sqlite3 and mcap storage, any ROS 2 distro
the bag declares, Jazzy message definitions by default).  Topics, under a namespace
(default ``/magcal``, docs/design.md §3):

- ``{ns}/sensor{j}/raw`` -- ``sensor_msgs/msg/MagneticField`` in tesla, sensor j's own
  axes (required, j = 1..S consecutive);
- ``{ns}/sensor{j}/temperature`` -- ``sensor_msgs/msg/Temperature`` in degC (optional);
- auxiliary channels: ``std_msgs/msg/Float64`` or ``Float32`` (``data``) on
  ``{ns}/aux/<name>`` (column ``aux_<name>``), or any topics named in ``aux_topics``;
- ``{ns}/ref_total`` -- ``std_msgs/msg/Float64``, scalar reference magnitude in tesla
  (optional);
- ``{ns}/imu`` (or ``imu_topic``) -- ``sensor_msgs/msg/Imu`` (optional): its ``orientation``
  is the body-to-world attitude of the array (REP 103/145; the IMU's axes are taken as the
  array's), interpolated (slerp) onto the epochs; epochs outside the IMU's time span are
  dropped and counted in ``meta['dropped_attitude_epochs']``.

Epochs are sensor 1's header stamps; each other sensor is matched to the nearest stamp
within half a sample period (epochs where a sensor has no match are dropped and counted in
``meta['dropped_epochs']``).  Temperatures and the reference are interpolated linearly onto
the epochs, auxiliary channels held from their last message (a switched current changes
when its message says so).  A message whose header stamp is zero is stamped with the time
the bag recorded it.  Tesla are converted to nT with :mod:`magcal_ros.units`.
"""
import os
from pathlib import Path
import re

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.units import nt_to_t, t_to_nt
import numpy as np

MAG_TYPE = 'sensor_msgs/msg/MagneticField'
TEMP_TYPE = 'sensor_msgs/msg/Temperature'
SCALAR_TYPES = ('std_msgs/msg/Float64', 'std_msgs/msg/Float32')
IMU_TYPE = 'sensor_msgs/msg/Imu'


class BagFormatError(ValueError):
    """The directory is not a usable rosbag2 recording of the array; the message says why."""


def _typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def _stamp(msg, recv_ns):
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return (ns if ns > 0 else int(recv_ns)) * 1e-9


def _hold(t_msg, v_msg, t):
    """Value of the last message at or before each time t (the first one before it)."""
    order = np.argsort(t_msg, kind='stable')
    t_msg, v_msg = t_msg[order], v_msg[order]
    i = np.searchsorted(t_msg, t, side='right') - 1
    return v_msg[np.clip(i, 0, len(v_msg) - 1)]


def _interp(t_msg, v_msg, t):
    order = np.argsort(t_msg, kind='stable')
    return np.interp(t, t_msg[order], v_msg[order])


def read_bag(path, namespace='/magcal', aux_topics=None, imu_topic=None):
    """
    Read a rosbag2 directory into a Dataset (readings in nT, times in s).

    Parameters
    ----------
    path : str or os.PathLike
        The bag directory (with ``metadata.yaml``).
    namespace : str
        Topic namespace of the array.
    aux_topics : dict of str to str, optional
        {column name ('aux_motor_current'): topic} for auxiliary channels published
        elsewhere (std_msgs Float64/Float32).
    imu_topic : str, optional
        ``sensor_msgs/Imu`` topic of the array's attitude (default ``{namespace}/imu``).

    Returns
    -------
    Dataset
        ``t`` (N,) s (header stamps, absolute), ``raw`` (S, N, 3) nT, ``temp`` (S, N) degC or
        None, ``ref_total`` (N,) nT or None, ``aux`` {name: (N,)}; ``meta`` holds the source,
        the topics used and the number of dropped epochs.

    """
    with _Collector(path, namespace, aux_topics, imu_topic) as col:
        for c, recv, data in col.reader.messages(connections=col.conns):
            col.add(c, recv, data)
        return col.take(None, final=True)


def bag_message_count(path):
    """Return the number of messages in a rosbag2 directory (from its ``metadata.yaml``)."""
    import yaml
    path = Path(os.fspath(path))
    try:
        with open(path / 'metadata.yaml') as fh:
            info = yaml.safe_load(fh)['rosbag2_bagfile_information']
        return int(info['message_count'])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise BagFormatError(f'{path} is not a rosbag2 directory (metadata.yaml: {exc})') \
            from None


def bag_epoch_count(path, namespace='/magcal'):
    """Messages of sensor 1 in a rosbag2 directory (its metadata), 0 when it does not say."""
    import yaml
    try:
        with open(Path(os.fspath(path)) / 'metadata.yaml') as fh:
            info = yaml.safe_load(fh)['rosbag2_bagfile_information']
        ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
        for entry in info.get('topics_with_message_count') or []:
            if entry['topic_metadata']['name'] == f'{ns}/sensor1/raw':
                return int(entry['message_count'])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError):
        pass
    return 0


def bag_chunks(path, rows=65536, progress=None, namespace='/magcal', aux_topics=None,
               imu_topic=None):
    """
    Yield the epochs of a rosbag2 recording as Datasets of about ``rows`` epochs, in order.

    The same epochs and values as :func:`read_bag` (the same pairing of the sensors' stamps
    within half a sample period, interpolation of the temperatures and the reference, hold
    of the auxiliary channels, slerp of the attitude), in memory bounded by ``rows``: the
    messages are read in the order the bag stores them and a chunk is made of the epochs of
    sensor 1 up to a time every stream has passed, keeping the messages around it that the
    next chunk needs.  The sample period is the median interval of sensor 1's stamps in the
    first chunk (:func:`read_bag`: of the whole record).  ``progress(messages read)``.
    """
    with _Collector(path, namespace, aux_topics, imu_topic) as col:
        n_msg = 0
        per_chunk = rows * max(1, len(col.conns))
        for c, recv, data in col.reader.messages(connections=col.conns):
            col.add(c, recv, data)
            n_msg += 1
            if n_msg % per_chunk == 0:
                piece = col.take(col.safe_time())
                if progress is not None:
                    progress(n_msg)
                if piece is not None:
                    yield piece
        piece = col.take(None, final=True)
        if progress is not None:
            progress(n_msg)
        if piece is not None:
            yield piece


class _Collector:
    """The messages of a bag's array topics, turned into epochs (all at once or in chunks)."""

    def __init__(self, path, namespace, aux_topics, imu_topic):
        from rosbags.highlevel import AnyReader
        path = Path(os.fspath(path))
        if not (path / 'metadata.yaml').is_file():
            raise BagFormatError(f'{path} is not a rosbag2 directory (no metadata.yaml)')
        self.path = path
        ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
        self.ns = ns
        self.raw_re = re.compile(re.escape(ns) + r'/sensor(\d+)/raw$')
        self.temp_re = re.compile(re.escape(ns) + r'/sensor(\d+)/temperature$')
        self.aux_re = re.compile(re.escape(ns) + r'/aux/(\w+)$')
        self.wanted_aux = {topic: (col if col.startswith('aux_') else 'aux_' + col)
                           for col, topic in (aux_topics or {}).items()}
        self.imu_name = imu_topic or ns + '/imu'
        self.imu = ([], [])
        try:
            self.reader = AnyReader([path], default_typestore=_typestore())
            self.reader.open()
        except Exception as exc:          # rosbags raises its own error types per storage
            raise BagFormatError(f'cannot open rosbag2 {path}: {exc}') from exc
        try:
            self._plan(imu_topic)
        except BaseException:
            self.reader.close()
            raise
        self.period = None
        self.dropped = 0
        self.dropped_att = 0
        self.emitted = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.reader.close()

    def _plan(self, imu_topic):
        """Choose the connections; map each to what it carries."""
        path, ns = self.path, self.ns
        self.mags, self.temps, self.aux, self.ref = {}, {}, {}, None
        self.kind = {}
        conns = []
        for c in self.reader.connections:
            m = self.raw_re.match(c.topic)
            if m and c.msgtype == MAG_TYPE:
                self.mags[int(m.group(1))] = ([], [])
                self.kind[c.id] = ('mag', int(m.group(1)))
                conns.append(c)
                continue
            if c.topic == self.imu_name and c.msgtype == IMU_TYPE:
                self.kind[c.id] = ('imu', None)
                conns.append(c)
                continue
            m = self.temp_re.match(c.topic)
            if m and c.msgtype == TEMP_TYPE:
                self.temps[int(m.group(1))] = ([], [])
                self.kind[c.id] = ('temp', int(m.group(1)))
                conns.append(c)
                continue
            if c.msgtype in SCALAR_TYPES:
                m = self.aux_re.match(c.topic)
                if c.topic in self.wanted_aux or m:
                    name = self.wanted_aux.get(c.topic) or 'aux_' + m.group(1)
                    self.aux[name] = ([], [])
                    self.kind[c.id] = ('aux', name)
                    conns.append(c)
                elif c.topic == ns + '/ref_total':
                    self.ref = ([], [])
                    self.kind[c.id] = ('ref', None)
                    conns.append(c)
        if not self.mags:
            topics = sorted(f'{c.topic} ({c.msgtype})' for c in self.reader.connections)
            raise BagFormatError(
                f'{path}: no {MAG_TYPE} topics named {ns}/sensor<j>/raw; the bag has: '
                f'{", ".join(topics) or "no topics"} (use namespace=...)')
        missing_aux = set(self.wanted_aux) - {c.topic for c in conns}
        if missing_aux:
            raise BagFormatError(f'{path}: auxiliary topic(s) {sorted(missing_aux)} not in the '
                                 'bag (or not std_msgs Float64/Float32)')
        if imu_topic and not any(c.topic == self.imu_name for c in conns):
            raise BagFormatError(f'{path}: no {IMU_TYPE} messages on {self.imu_name}')
        self.conns = conns
        self.topics = sorted(c.topic for c in conns)

    def add(self, c, recv, data):
        """Take one message (connection, receive time ns, serialised bytes)."""
        msg = self.reader.deserialize(data, c.msgtype)
        kind, key = self.kind[c.id]
        if kind == 'mag':
            v = msg.magnetic_field
            self.mags[key][0].append(_stamp(msg, recv))
            self.mags[key][1].append((v.x, v.y, v.z))
        elif kind == 'temp':
            self.temps[key][0].append(_stamp(msg, recv))
            self.temps[key][1].append(msg.temperature)
        elif kind == 'imu':
            if msg.orientation_covariance[0] == -1:
                raise BagFormatError(
                    f'{self.path}: {self.imu_name}: the Imu messages carry no orientation '
                    '(orientation_covariance[0] = -1); record an orientation estimate')
            o = msg.orientation
            self.imu[0].append(_stamp(msg, recv))
            self.imu[1].append((o.w, o.x, o.y, o.z))
        elif kind == 'ref':
            self.ref[0].append(recv * 1e-9)
            self.ref[1].append(msg.data)
        else:
            self.aux[key][0].append(recv * 1e-9)
            self.aux[key][1].append(msg.data)

    def safe_time(self):
        """Latest time every sensor stream has passed by half a period (None: not yet)."""
        lasts = [max(tt) for tt, _ in self.mags.values() if tt]
        if len(lasts) < len(self.mags) or not self.mags[1][0]:
            return None
        for tt, _ in list(self.temps.values()) + [self.imu]:
            if tt:
                lasts.append(max(tt))
        if self.period is None:
            t1 = np.sort(np.asarray(self.mags[1][0], float))
            if len(t1) < 2:
                return None
            self.period = float(np.median(np.diff(t1)))
        return min(lasts) - 2 * self.period

    def take(self, upto, final=False):
        """
        Return the epochs of sensor 1 up to time ``upto`` (all when ``final``) as a Dataset.

        Keeps the messages the later epochs still need (those within a few periods before
        ``upto``; the last message before it of the held and interpolated channels).
        """
        if not final and upto is None:
            return None
        path, ns = self.path, self.ns
        s = max(self.mags)
        absent = [j for j in range(1, s + 1) if j not in self.mags or not self.mags[j][0]]
        if any(j not in self.mags for j in absent) or (absent and final and not self.emitted):
            names = ', '.join(f'{ns}/sensor{j}/raw' for j in absent)
            raise BagFormatError(f'{path}: no messages on {names} (sensors must be numbered '
                                 f'1..{s})')
        t1 = np.asarray(self.mags[1][0], float)
        order = np.argsort(t1, kind='stable')
        t_all = t1[order]
        if final and not self.emitted and len(t_all) < 2:
            raise BagFormatError(f'{path}: sensor 1 has only {len(t_all)} message(s)')
        period = self.period
        if period is None:
            period = float(np.median(np.diff(t_all))) if len(t_all) > 1 else 0.0
        sel = np.ones(len(t_all), bool) if final else t_all <= upto
        t = t_all[sel]
        v1 = np.asarray(self.mags[1][1], float).reshape(-1, 3)[order]
        raw = np.empty((s, len(t), 3))
        raw[0] = v1[sel]
        keep = np.ones(len(t), bool)
        for j in range(2, s + 1):
            tj = np.asarray(self.mags[j][0], float)
            vj = np.asarray(self.mags[j][1], float).reshape(-1, 3)
            oj = np.argsort(tj, kind='stable')
            tj, vj = tj[oj], vj[oj]
            if len(tj) == 0:
                keep[:] = False
                continue
            i = np.clip(np.searchsorted(tj, t), 1, len(tj) - 1) if len(tj) > 1 else np.zeros(
                len(t), int)
            if len(tj) > 1:
                i = np.where(np.abs(tj[i - 1] - t) <= np.abs(tj[i] - t), i - 1, i)
            keep &= np.abs(tj[i] - t) <= 0.5 * period + 1e-9
            raw[j - 1] = vj[i]
        raw = t_to_nt(raw)
        self.dropped += int((~keep).sum())
        t, raw = t[keep], raw[:, keep]
        if final and not self.emitted and len(t) < 2:
            raise BagFormatError(f'{path}: the stamps of the {s} sensors do not match (no '
                                 'common epochs within half a sample period)')
        temp = None
        if self.temps:
            temp = np.full((s, len(t)), np.nan)
            for j, (tt, vv) in self.temps.items():
                if 1 <= j <= s and tt:
                    temp[j - 1] = _interp(np.asarray(tt), np.asarray(vv, float), t)
        aux_out = {k: _hold(np.asarray(tt), np.asarray(vv, float), t)
                   for k, (tt, vv) in self.aux.items() if tt}
        ref_total = None
        if self.ref is not None and self.ref[0]:
            ref_total = t_to_nt(_interp(np.asarray(self.ref[0]), np.asarray(self.ref[1], float),
                                        t))
        data = Dataset(t=t, raw=raw, temp=temp, ref_total=ref_total, aux=aux_out,
                       meta={'source': str(path), 'namespace': ns or '/',
                             'dropped_epochs': self.dropped, 'topics': self.topics})
        if self.imu[0] and len(t):
            from magcal_ros.core.geometry.attitude import with_attitude
            try:
                data, kept = with_attitude(data, self.imu[0], self.imu[1],
                                           source=f'{path}: {self.imu_name}')
            except ValueError as exc:
                raise BagFormatError(str(exc)) from None
            self.dropped_att += int((~kept).sum())
            data.meta['dropped_attitude_epochs'] = self.dropped_att
        if not final:
            self._forget(upto, period)
        if data.n_samples == 0:
            return None
        self.emitted = True
        return data

    def _forget(self, upto, period):
        """Drop the messages no epoch after ``upto`` needs."""
        margin = upto - 4 * period

        def trim(tt_vv, hold_one=True):
            tt, vv = tt_vv
            if not tt:
                return tt_vv
            ta = np.asarray(tt, float)
            later = np.flatnonzero(ta > margin)
            if hold_one:
                before = np.flatnonzero(ta <= margin)
                if len(before):
                    later = np.concatenate([[before[np.argmax(ta[before])]], later])
            return ([tt[i] for i in later], [vv[i] for i in later])
        t1 = np.asarray(self.mags[1][0], float)
        rest = np.flatnonzero(t1 > upto)
        self.mags[1] = ([self.mags[1][0][i] for i in rest], [self.mags[1][1][i] for i in rest])
        for j in list(self.mags):
            if j != 1:
                self.mags[j] = trim(self.mags[j], hold_one=False)
        for j in list(self.temps):
            self.temps[j] = trim(self.temps[j])
        for k in list(self.aux):
            self.aux[k] = trim(self.aux[k])
        if self.ref is not None:
            self.ref = trim(self.ref)
        self.imu = trim(self.imu)


def write_bag(path, data, namespace='/magcal', storage='sqlite3', frame_id='fluxgate'):
    """
    Write a Dataset as a rosbag2 recording in the layout :func:`read_bag` reads.

    For tests, demos and converting CSV recordings for ROS tools.  Readings are written in
    tesla (``sensor_msgs/MagneticField``), temperatures in degC, auxiliary channels as
    ``std_msgs/Float64`` on ``{ns}/aux/<name>``, ``ref_total`` in tesla.

    Parameters
    ----------
    path : str or os.PathLike
        Bag directory to create (must not exist).
    data : Dataset or iterable of Dataset
        Times ``t`` (N,) s are used as header stamps and receive times; an iterable of
        consecutive pieces with the same columns (a long record, chunk by chunk) is written
        as one recording.
    namespace : str
        Topic namespace (topics ``{namespace}/sensor{j}/raw``, ...).
    storage : {'sqlite3', 'mcap'}
        rosbag2 storage plug-in.
    frame_id : str
        Header frame prefix; sensor j gets ``{frame_id}{j}``.

    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugins = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}
    if storage not in plugins:
        raise ValueError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}")
    path = Path(os.fspath(path))
    if path.exists():
        raise ValueError(f'{path} exists: rosbag2 writes a new directory')
    from itertools import chain
    pieces = iter([data] if isinstance(data, Dataset) else data)
    first = next(pieces)
    ts = _typestore()
    mag_cls = ts.types[MAG_TYPE]
    temp_cls = ts.types[TEMP_TYPE]
    f64 = ts.types['std_msgs/msg/Float64']
    header = ts.types['std_msgs/msg/Header']
    stamp_cls = ts.types['builtin_interfaces/msg/Time']
    vec = ts.types['geometry_msgs/msg/Vector3']
    imu_cls = ts.types[IMU_TYPE]
    quat = ts.types['geometry_msgs/msg/Quaternion']
    unknown = np.array([-1.0] + [0.0] * 8)       # REP 145: no rate / acceleration
    ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
    cov = np.zeros(9)
    with Writer(path, version=9, storage_plugin=plugins[storage]) as w:
        conn = {}
        for j in range(1, first.n_sensors + 1):
            conn[('raw', j)] = w.add_connection(f'{ns}/sensor{j}/raw', MAG_TYPE, typestore=ts)
            if first.temp is not None and np.isfinite(first.temp[j - 1]).any():
                conn[('temp', j)] = w.add_connection(f'{ns}/sensor{j}/temperature', TEMP_TYPE,
                                                     typestore=ts)
        for name in sorted(first.aux):
            conn[('aux', name)] = w.add_connection(f'{ns}/aux/{name[4:]}',
                                                   'std_msgs/msg/Float64', typestore=ts)
        if first.ref_total is not None:
            conn[('ref',)] = w.add_connection(f'{ns}/ref_total', 'std_msgs/msg/Float64',
                                              typestore=ts)
        if first.attitude is not None:
            conn[('imu',)] = w.add_connection(f'{ns}/imu', IMU_TYPE, typestore=ts)
        for data in chain([first], pieces):
            t_ns = np.round(np.asarray(data.t, float) * 1e9).astype(np.int64)
            raw_t = nt_to_t(data.raw)
            for k in range(data.n_samples):
                st = stamp_cls(sec=int(t_ns[k] // 1_000_000_000),
                               nanosec=int(t_ns[k] % 1_000_000_000))
                for j in range(1, data.n_sensors + 1):
                    hdr = header(stamp=st, frame_id=f'{frame_id}{j}')
                    msg = mag_cls(header=hdr, magnetic_field=vec(*map(float, raw_t[j - 1, k])),
                                  magnetic_field_covariance=cov)
                    w.write(conn[('raw', j)], int(t_ns[k]), ts.serialize_cdr(msg, MAG_TYPE))
                    if ('temp', j) in conn:
                        msg = temp_cls(header=hdr, temperature=float(data.temp[j - 1, k]),
                                       variance=0.0)
                        w.write(conn[('temp', j)], int(t_ns[k]),
                                ts.serialize_cdr(msg, TEMP_TYPE))
                for name in sorted(data.aux):
                    w.write(conn[('aux', name)], int(t_ns[k]),
                            ts.serialize_cdr(f64(data=float(data.aux[name][k])),
                                             'std_msgs/msg/Float64'))
                if ('ref',) in conn:
                    w.write(conn[('ref',)], int(t_ns[k]),
                            ts.serialize_cdr(f64(data=float(nt_to_t(data.ref_total[k]))),
                                             'std_msgs/msg/Float64'))
                if ('imu',) in conn:
                    qw, qx, qy, qz = map(float, data.attitude[k])
                    msg = imu_cls(header=header(stamp=st, frame_id=frame_id),
                                  orientation=quat(x=qx, y=qy, z=qz, w=qw),
                                  orientation_covariance=np.zeros(9),
                                  angular_velocity=vec(0.0, 0.0, 0.0),
                                  angular_velocity_covariance=unknown,
                                  linear_acceleration=vec(0.0, 0.0, 0.0),
                                  linear_acceleration_covariance=unknown)
                    w.write(conn[('imu',)], int(t_ns[k]), ts.serialize_cdr(msg, IMU_TYPE))
    return path
