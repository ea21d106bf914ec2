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

Read with the ``rosbags`` library (sqlite3 and mcap, Jazzy message definitions).  Topics
under a namespace (default ``/magcal``, docs/design.md §3): ``{ns}/sensor{j}/raw``
(MagneticField, T; j = 1..S), ``{ns}/sensor{j}/temperature`` (degC), Float64/Float32
``{ns}/aux/<name>`` (column ``aux_<name>``) or ``aux_topics``, ``{ns}/ref_total`` (T),
``{ns}/imu`` or ``imu_topic`` (the body-to-world attitude, slerped; epochs outside its span
counted in ``meta['dropped_attitude_epochs']``), and any BatteryState topic
(``aux_battery_current`` A, ``aux_battery_voltage`` V; a second, in name order,
``aux_battery2_...``; NaN left out).

Epochs are sensor 1's header stamps (zero: the recording time); each other sensor is matched
to the nearest stamp within half a sample period (else dropped, ``meta['dropped_epochs']``).
Temperatures and the reference are interpolated linearly, auxiliary channels held.  The
fixed-layout messages are decoded from their CDR layout (docs/design.md §2), BatteryState by
rosbags.
"""
from itertools import islice
from operator import attrgetter, itemgetter
import os
from pathlib import Path
import re

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.units import nt_to_t, t_to_nt
import numpy as np

_CONN, _RECV, _DATA = itemgetter(0), itemgetter(1), itemgetter(2)
_ID = attrgetter('id')

MAG_TYPE = 'sensor_msgs/msg/MagneticField'
TEMP_TYPE = 'sensor_msgs/msg/Temperature'
SCALAR_TYPES = ('std_msgs/msg/Float64', 'std_msgs/msg/Float32')
IMU_TYPE = 'sensor_msgs/msg/Imu'
BATTERY_TYPE = 'sensor_msgs/msg/BatteryState'


class BagFormatError(ValueError):
    """The directory is not a usable rosbag2 recording of the array; the message says why."""


def _typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def _hold(t_msg, v_msg, t):
    """Value of the last message at or before each time t (the first one before it)."""
    order = np.argsort(t_msg, kind='stable')
    i = np.searchsorted(t_msg[order], t, side='right') - 1
    return v_msg[order][np.clip(i, 0, len(v_msg) - 1)]


def _interp(t_msg, v_msg, t):
    order = np.argsort(t_msg, kind='stable')
    return np.interp(t, t_msg[order], v_msg[order])


def read_bag(path, namespace='/magcal', aux_topics=None, imu_topic=None):
    """
    Read a rosbag2 directory (with ``metadata.yaml``) into a Dataset.

    ``aux_topics`` {column name ('aux_motor_current'): topic} of Float64/Float32 channels
    published elsewhere; ``imu_topic`` the Imu topic (default ``{namespace}/imu``).  Returns
    ``t`` (N,) s (header stamps), ``raw`` (S, N, 3) nT, ``temp`` (S, N) degC or None,
    ``ref_total`` (N,) nT or None, ``aux`` {name: (N,)}, ``attitude`` (N, 4) or None;
    ``meta`` the source, the topics used and the dropped epochs.
    """
    with _Collector(path, namespace, aux_topics, imu_topic) as col:
        messages = col.reader.messages(connections=col.conns)
        while col.read(messages, col.FLUSH):
            pass
        return col.take(None, final=True)


def _metadata(path, read):
    """``read(the bag's rosbag2_bagfile_information)``; its exception when that fails."""
    import yaml
    try:
        with open(Path(os.fspath(path)) / 'metadata.yaml') as fh:
            return read(yaml.safe_load(fh)['rosbag2_bagfile_information'])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        return exc


def bag_message_count(path):
    """Return the number of messages in a rosbag2 directory (from its ``metadata.yaml``)."""
    got = _metadata(path, lambda info: int(info['message_count']))
    if isinstance(got, Exception):
        raise BagFormatError(f'{Path(os.fspath(path))} is not a rosbag2 directory '
                             f'(metadata.yaml: {got})')
    return got


def bag_epoch_count(path, namespace='/magcal'):
    """Messages of sensor 1 in a rosbag2 directory (its metadata), 0 when it does not say."""
    topic = f'{_namespace(namespace)}/sensor1/raw'
    got = _metadata(path, lambda info: next(
        (int(e['message_count']) for e in info.get('topics_with_message_count') or []
         if e['topic_metadata']['name'] == topic), 0))
    return 0 if isinstance(got, Exception) else got


def _namespace(namespace):
    """'/magcal' of 'magcal', '/magcal/' or '/magcal'; '' of '/'."""
    return '/' + namespace.strip('/') if namespace.strip('/') else ''


def bag_chunks(path, rows=65536, progress=None, namespace='/magcal', aux_topics=None,
               imu_topic=None):
    """
    Yield the epochs of a rosbag2 recording as Datasets of about ``rows`` epochs, in order.

    The epochs and values of :func:`read_bag`, in memory bounded by ``rows``: a chunk is
    sensor 1's epochs up to a time every stream has passed, the messages the next chunk
    needs kept.  The sample period is the median of sensor 1's intervals in the first chunk
    (:func:`read_bag`: the whole record).  ``progress(messages read)``.
    """
    with _Collector(path, namespace, aux_topics, imu_topic, rows) as col:
        n_msg, done = 0, False
        per_chunk = rows * max(1, len(col.conns))
        messages = col.reader.messages(connections=col.conns)
        while not done:
            # a chunk every per_chunk messages (and at the end), read and decoded FLUSH at a time
            got = col.read(messages, min(col.FLUSH, per_chunk - n_msg % per_chunk))
            n_msg += got
            done = got == 0
            if done or n_msg % per_chunk == 0:
                piece = col.take(None, final=True) if done else col.take(col.safe_time())
                if progress is not None:
                    progress(n_msg)
                if piece is not None:
                    yield piece


#: The message types read without rosbags' deserialiser (their CDR layout: docs/design.md
#: §2): {type: (has a Header, bytes after it (the whole payload without one), float fields
#: read at the start of those bytes, their CDR type)}.
_LAYOUT = {
    MAG_TYPE: (True, 96, 3, 'f8'),
    TEMP_TYPE: (True, 16, 1, 'f8'),
    IMU_TYPE: (True, 296, 5, 'f8'),          # orientation x, y, z, w, covariance[0]
    'std_msgs/msg/Float64': (False, 8, 1, 'f8'),
    'std_msgs/msg/Float32': (False, 4, 1, 'f4'),
}


def _dtype(msgtype, order, n, k):
    """
    Return the dtype of an ``n``-byte message: ``v`` its first ``k`` floats after the header.

    With a header also ``sec``, ``nsec`` and ``len`` (of frame_id); ``order`` '<' or '>'.
    """
    has_header, tail, _, kind = _LAYOUT[msgtype]
    names, formats, offsets = ['v'], [(order + kind, (k,))], [n - tail]
    if has_header:
        names += ['sec', 'nsec', 'len']
        formats += [order + 'i4', order + 'u4', order + 'u4']
        offsets += [4, 8, 12]
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': n})


def _decode_fixed(datas, msgtype):
    """
    Decode M serialised messages ``datas`` of a type in ``_LAYOUT``, by length, with numpy.

    Only plain CDR of the exact length its frame_id (non-empty, NUL-terminated, ASCII) makes
    is decoded here; the rest is left to rosbags.  Returns (stamp_ns (M,) int64, None without
    a header; values (M, k), message units; ok (M,) bool, False where not decoded).
    """
    has_header, tail, k, kind = _LAYOUT[msgtype]
    m = len(datas)
    stamp = np.zeros(m, np.int64) if has_header else None
    values = np.zeros((m, k))
    ok = np.zeros(m, bool)
    lens = np.fromiter(map(len, datas), np.int64, m)
    sizes = np.unique(lens)
    for n in sizes.tolist():
        if n < 4 + tail + (16 if has_header else 0):
            continue
        idx = np.flatnonzero(lens == n) if len(sizes) > 1 else np.arange(m)
        buf = b''.join([datas[i] for i in idx]) if len(sizes) > 1 else b''.join(datas)
        raw = np.frombuffer(buf, np.uint8).reshape(len(idx), n)
        for order, flag in (('<', 1), ('>', 0)):
            rows = np.flatnonzero((raw[:, 0] == 0) & (raw[:, 1] == flag))
            if not len(rows):
                continue
            rec = np.frombuffer(buf, _dtype(msgtype, order, n, k))[rows]
            good = np.ones(len(rows), bool)
            if has_header:
                length = rec['len'].astype(np.int64)
                # float64 fields start at 4 + the next multiple of 8 after 12 + length
                good = (length >= 1) & (4 + (12 + length + 7) // 8 * 8 + tail == n)
                nul = np.minimum(15 + length, n - 1)
                good &= raw[rows, nul] == 0
                cols = np.arange(16, n - tail)
                text = cols[None, :] < (15 + length)[:, None]
                good &= ~((raw[rows, 16:n - tail] >= 0x80) & text).any(axis=1)
                stamp[idx[rows[good]]] = (rec['sec'][good].astype(np.int64) * 1_000_000_000
                                          + rec['nsec'][good].astype(np.int64))
            values[idx[rows[good]]] = rec['v'][good].astype(np.float64)
            ok[idx[rows[good]]] = True
    return stamp, values, ok


#: the fields read of a message rosbags decoded, by type (std_msgs: ``data``, no header)
_FIELDS = {MAG_TYPE: attrgetter('magnetic_field.x', 'magnetic_field.y', 'magnetic_field.z'),
           TEMP_TYPE: attrgetter('temperature'),
           IMU_TYPE: attrgetter('orientation.x', 'orientation.y', 'orientation.z',
                                'orientation.w', 'orientation_covariance'),
           BATTERY_TYPE: attrgetter('current', 'voltage')}


def _message_values(msg, msgtype):
    """Return (stamp ns or None, the fields read) of a message rosbags decoded."""
    if msgtype not in _FIELDS:
        return None, (msg.data,)
    vals = _FIELDS[msgtype](msg)
    if msgtype == IMU_TYPE:
        vals = vals[:4] + (vals[4][0],)
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec), vals


class _Collector:
    """The messages of a bag's array topics, turned into epochs (all at once or in chunks)."""

    #: messages read and decoded at a time (held serialised meanwhile: ~150 bytes each)
    FLUSH = 65536

    def __init__(self, path, namespace, aux_topics, imu_topic, rows=None):
        from rosbags.highlevel import AnyReader
        path = Path(os.fspath(path))
        if not (path / 'metadata.yaml').is_file():
            raise BagFormatError(f'{path} is not a rosbag2 directory (no metadata.yaml)')
        self.path = path
        self.ns = ns = _namespace(namespace)
        self.raw_re = re.compile(re.escape(ns) + r'/sensor(\d+)/raw$')
        self.temp_re = re.compile(re.escape(ns) + r'/sensor(\d+)/temperature$')
        self.aux_re = re.compile(re.escape(ns) + r'/aux/(\w+)$')
        self.wanted_aux = {topic: (col if col.startswith('aux_') else 'aux_' + col)
                           for col, topic in (aux_topics or {}).items()}
        self.imu_name = imu_topic or ns + '/imu'
        self.imu = _empty(4)
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
        self.period = self.t1_first = None
        self.rows = rows
        self.dropped = self.dropped_att = 0
        self.emitted = False
        self.n_decoded = {c.id: 0 for c in self.conns}

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
            raw, temp = self.raw_re.match(c.topic), self.temp_re.match(c.topic)
            aux = self.aux_re.match(c.topic)
            if raw and c.msgtype == MAG_TYPE:
                self.mags[int(raw.group(1))] = _empty(3)
                self.kind[c.id] = ('mag', int(raw.group(1)))
            elif c.topic == self.imu_name and c.msgtype == IMU_TYPE:
                self.kind[c.id] = ('imu', None)
            elif temp and c.msgtype == TEMP_TYPE:
                self.temps[int(temp.group(1))] = _empty()
                self.kind[c.id] = ('temp', int(temp.group(1)))
            elif c.msgtype in SCALAR_TYPES and (c.topic in self.wanted_aux or aux):
                name = self.wanted_aux.get(c.topic) or 'aux_' + aux.group(1)
                self.aux[name] = _empty()
                self.kind[c.id] = ('aux', name)
            elif c.msgtype in SCALAR_TYPES and c.topic == ns + '/ref_total':
                self.ref = _empty()
                self.kind[c.id] = ('ref', None)
            else:
                continue
            conns.append(c)
        batteries = sorted({c.topic for c in self.reader.connections
                            if c.msgtype == BATTERY_TYPE})
        for c in self.reader.connections:
            if c.msgtype == BATTERY_TYPE:
                k = batteries.index(c.topic)
                tag = 'aux_battery' if k == 0 else f'aux_battery{k + 1}'
                for what in ('current', 'voltage'):
                    self.aux.setdefault(f'{tag}_{what}', _empty())
                self.kind[c.id] = ('battery', tag)
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
        self.by_id = {c.id: c for c in conns}
        self.topics = sorted(c.topic for c in conns)

    def read(self, messages, count):
        """
        Read and decode up to ``count`` messages of rosbags' ``AnyReader.messages()``.

        Sorted by connection with numpy, no Python code per message.  Returns how many were
        read (0: the bag is done).
        """
        batch = list(islice(messages, count))
        m = len(batch)
        if m == 0:
            return 0
        ids = np.fromiter(map(_ID, map(_CONN, batch)), np.int64, m)
        recv = np.fromiter(map(_RECV, batch), np.int64, m)
        datas = list(map(_DATA, batch))
        del batch
        for cid in np.unique(ids).tolist():
            idx = np.flatnonzero(ids == cid)
            if len(idx) == m:
                self._decode(self.by_id[cid], datas, recv)
            else:
                got = itemgetter(*idx.tolist())(datas)
                self._decode(self.by_id[cid], list(got) if len(idx) > 1 else [got], recv[idx])
        return m

    def _decode(self, c, datas, recv):
        if c.msgtype in _LAYOUT:
            stamp, vals, ok = _decode_fixed(datas, c.msgtype)
        else:                                   # BatteryState: rosbags decodes each
            stamp, vals = np.zeros(len(datas), np.int64), np.zeros((len(datas), 2))
            ok = np.zeros(len(datas), bool)
        for i in np.flatnonzero(~ok).tolist():
            try:
                msg = self.reader.deserialize(datas[i], c.msgtype)
            except Exception as exc:      # rosbags' own error types
                first = self.n_decoded[c.id] + 1
                raise BagFormatError(
                    f'{self.path}: message {first + i} of {c.topic} ({c.msgtype}, recorded '
                    f'at {int(recv[i])} ns) cannot be decoded ({exc}): the recording is '
                    'damaged there; re-record it, or leave this topic out (e.g. namespace=, '
                    'aux_topics=) or copy the bag without it (ros2 bag convert)') from None
            st, v = _message_values(msg, c.msgtype)
            if stamp is not None:
                stamp[i] = st
            vals[i] = v
        self.n_decoded[c.id] += len(datas)
        kind, key = self.kind[c.id]
        t = (recv if stamp is None else np.where(stamp > 0, stamp, recv)) * 1e-9
        if kind == 'mag':
            if key == 1 and self.t1_first is None and len(t):
                self.t1_first = float(t.min())
            self.mags[key] = _extend(self.mags[key], t, vals)
        elif kind == 'temp':
            self.temps[key] = _extend(self.temps[key], t, vals[:, 0])
        elif kind == 'imu':
            if (vals[:, 4] == -1).any():
                raise BagFormatError(
                    f'{self.path}: {self.imu_name}: the Imu messages carry no orientation '
                    '(orientation_covariance[0] = -1); record an orientation estimate')
            self.imu = _extend(self.imu, t, vals[:, [3, 0, 1, 2]])
        elif kind == 'ref':
            self.ref = _extend(self.ref, t, vals[:, 0])
        elif kind == 'battery':
            for col, what in ((0, 'current'), (1, 'voltage')):
                fin = np.isfinite(vals[:, col])
                name = f'{key}_{what}'
                self.aux[name] = _extend(self.aux[name], t[fin], vals[fin, col])
        else:
            self.aux[key] = _extend(self.aux[key], t, vals[:, 0])

    def safe_time(self):
        """
        Latest time every sensor stream has passed by half a period (None: not yet).

        A stream more than ``rows`` periods behind sensor 1 (stopped, or a gap that long) is
        not waited for, so the messages held stay about a chunk's; across such a gap a
        temperature is held and epochs lose their attitude (:func:`read_bag` interpolates).
        """
        t1 = self.mags[1][0]
        if not len(t1):
            return None
        if self.period is None:
            if len(t1) < 2:
                return None
            self.period = float(np.median(np.diff(np.sort(t1))))
        now = float(t1.max())
        horizon = np.inf if self.rows is None else self.rows * self.period
        lasts = [now]
        for tt, _ in self.mags.values():
            if not len(tt):
                if now - self.t1_first <= horizon:
                    return None
            elif tt.max() >= now - horizon:
                lasts.append(float(tt.max()))
        for tt, _ in list(self.temps.values()) + [self.imu]:
            if len(tt) and tt.max() >= now - horizon:
                lasts.append(float(tt.max()))
        return min(lasts) - 2 * self.period

    def take(self, upto, final=False):
        """Return sensor 1's epochs up to ``upto`` (all when ``final``) as a Dataset, or None."""
        if not final and upto is None:
            return None
        path, ns = self.path, self.ns
        s = max(self.mags)
        absent = [j for j in range(1, s + 1) if j not in self.mags or not len(self.mags[j][0])]
        if any(j not in self.mags for j in absent) or (absent and final and not self.emitted):
            names = ', '.join(f'{ns}/sensor{j}/raw' for j in absent)
            raise BagFormatError(f'{path}: no messages on {names} (sensors must be numbered '
                                 f'1..{s})')
        t1 = self.mags[1][0]
        order = np.argsort(t1, kind='stable')
        t_all = t1[order]
        if final and not self.emitted and len(t_all) < 2:
            raise BagFormatError(f'{path}: sensor 1 has only {len(t_all)} message(s)')
        period = self.period
        if period is None:
            period = float(np.median(np.diff(t_all))) if len(t_all) > 1 else 0.0
        sel = np.ones(len(t_all), bool) if final else t_all <= upto
        t = t_all[sel]
        raw = np.zeros((s, len(t), 3))         # a sensor without messages: all dropped
        raw[0] = self.mags[1][1][order][sel]
        keep = np.ones(len(t), bool)
        for j in range(2, s + 1):
            tj, vj = self.mags[j]
            oj = np.argsort(tj, kind='stable')
            tj, vj = tj[oj], vj[oj]
            if len(tj) == 0:
                keep[:] = False
                continue
            # the nearest message (one message: the clip gives 0, and -1 is that message too)
            i = np.clip(np.searchsorted(tj, t), 1, len(tj) - 1)
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
                if 1 <= j <= s and len(tt):
                    temp[j - 1] = _interp(tt, vv, t)
        aux_out = {k: _hold(tt, vv, t) for k, (tt, vv) in self.aux.items() if len(tt)}
        ref_total = (t_to_nt(_interp(*self.ref, t)) if self.ref is not None and len(self.ref[0])
                     else None)
        data = Dataset(t=t, raw=raw, temp=temp, ref_total=ref_total, aux=aux_out,
                       meta={'source': str(path), 'namespace': ns or '/',
                             'dropped_epochs': self.dropped, 'topics': self.topics})
        if len(self.imu[0]) and len(t):
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
            if not len(tt):
                return tt_vv
            later = np.flatnonzero(tt > margin)
            if hold_one:
                before = np.flatnonzero(tt <= margin)
                if len(before):
                    later = np.concatenate([[before[np.argmax(tt[before])]], later])
            return tt[later], vv[later]
        t1, v1 = self.mags[1]
        rest = np.flatnonzero(t1 > upto)
        self.mags[1] = (t1[rest], v1[rest])
        self.mags.update({j: trim(tv, hold_one=False) for j, tv in self.mags.items() if j != 1})
        self.temps = {j: trim(tv) for j, tv in self.temps.items()}
        self.aux = {k: trim(tv) for k, tv in self.aux.items()}
        self.ref = None if self.ref is None else trim(self.ref)
        self.imu = trim(self.imu)


def _empty(k=None):
    """Return (times (0,) s, values (0,) or (0, k)) of a stream with no message yet."""
    return np.empty(0), np.empty((0, k) if k else 0)


def _extend(stream, t, v):
    """Return the stream with messages (times t (M,) s, values v (M, ...)) appended."""
    return np.concatenate([stream[0], t]), np.concatenate([stream[1], v])


def write_bag(path, data, namespace='/magcal', storage='sqlite3', frame_id='fluxgate'):
    """
    Write a Dataset as a rosbag2 recording in the layout :func:`read_bag` reads.

    ``path`` the bag directory to create (must not exist); ``data`` a Dataset or consecutive
    pieces with the same columns, ``t`` (N,) s the stamps and receive times; ``storage``
    'sqlite3' or 'mcap'; ``frame_id`` the header frame prefix (sensor j: ``{frame_id}{j}``).
    Returns the path.
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
    header = ts.types['std_msgs/msg/Header']
    stamp0 = ts.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0)
    vec = ts.types['geometry_msgs/msg/Vector3']
    unknown = np.array([-1.0] + [0.0] * 8)       # REP 145: no rate / acceleration
    ns = _namespace(namespace)
    f64 = 'std_msgs/msg/Float64'
    # one message of each stream serialised by rosbags, stamps and values filled in (_Template)
    with Writer(path, version=9, storage_plugin=plugins[storage]) as w:
        streams = []

        def add(get, topic, msgtype, **fields):
            """Add a stream: ``get(piece)`` its values, one template message of its type."""
            streams.append((get, w.add_connection(topic, msgtype, typestore=ts),
                            _Template(ts, msgtype, ts.types[msgtype](**fields))))
        for j in range(1, first.n_sensors + 1):
            hdr = header(stamp=stamp0, frame_id=f'{frame_id}{j}')
            add(lambda d, j=j: nt_to_t(d.raw[j - 1]), f'{ns}/sensor{j}/raw', MAG_TYPE,
                header=hdr, magnetic_field=vec(0.0, 0.0, 0.0),
                magnetic_field_covariance=np.zeros(9))
            if first.temp is not None and np.isfinite(first.temp[j - 1]).any():
                add(lambda d, j=j: d.temp[j - 1], f'{ns}/sensor{j}/temperature', TEMP_TYPE,
                    header=hdr, temperature=0.0, variance=0.0)
        for name in sorted(first.aux):
            add(lambda d, name=name: d.aux[name], f'{ns}/aux/{name[4:]}', f64, data=0.0)
        if first.ref_total is not None:
            add(lambda d: nt_to_t(d.ref_total), f'{ns}/ref_total', f64, data=0.0)
        if first.attitude is not None:
            quat = ts.types['geometry_msgs/msg/Quaternion']
            # Dataset: w x y z; Imu: x y z w
            add(lambda d: np.asarray(d.attitude, float)[:, [1, 2, 3, 0]], f'{ns}/imu', IMU_TYPE,
                header=header(stamp=stamp0, frame_id=frame_id),
                orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9), angular_velocity=vec(0.0, 0.0, 0.0),
                angular_velocity_covariance=unknown, linear_acceleration=vec(0.0, 0.0, 0.0),
                linear_acceleration_covariance=unknown)
        for data in chain([first], pieces):
            t_ns = np.round(np.asarray(data.t, float) * 1e9).astype(np.int64)
            columns = [(conn, tmpl.messages(t_ns, get(data))) for get, conn, tmpl in streams]
            for k, tk in enumerate(t_ns.tolist()):
                for conn, msgs in columns:
                    w.write(conn, tk, msgs[k])
    return path


class _Template:
    """Serialised messages of one type that differ only in their stamp and leading fields."""

    def __init__(self, ts, msgtype, msg):
        self.raw = np.frombuffer(ts.serialize_cdr(msg, msgtype), np.uint8)
        self.has_header = _LAYOUT[msgtype][0]
        self.dtype = _dtype(msgtype, '<' if self.raw[1] == 1 else '>', len(self.raw),
                            {MAG_TYPE: 3, IMU_TYPE: 4}.get(msgtype, 1))

    def messages(self, t_ns, values):
        """Return M serialised copies (bytes): stamps t_ns (M,) ns, ``values`` (M, w) floats."""
        n, m = len(self.raw), len(t_ns)
        buf = np.tile(self.raw, m)
        rec = buf.view(self.dtype)
        if self.has_header:
            rec['sec'] = t_ns // 1_000_000_000
            rec['nsec'] = t_ns % 1_000_000_000
        rec['v'] = np.asarray(values, float).reshape(m, -1)
        blob = buf.tobytes()
        return [blob[i:i + n] for i in range(0, m * n, n)]
