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
Writers of small ArduPilot DataFlash and PX4 ULog files with known content (tests, bench).

Written from the formats' documentation, not with the readers under test: a DataFlash
message is 0xA3 0x95, its type byte and its fields packed little endian as its FMT message
says (FMT itself: type 128, 89 bytes, 'BBnNZ'; ArduPilot's LogStructure.h); a ULog file is
the 16-byte header ('ULog' 01 12 35, version, start time in us) and messages of a 3-byte
header (uint16 size, uint8 type): 'F' formats, 'I' information, 'P' parameters, 'A'
subscriptions and 'D' data (PX4 docs, "ULog File Format").  A text DataFlash log is the
same messages as comma-separated lines (pymavlink's DFReader_text reads it).
"""
import struct

import numpy as np

#: DataFlash format characters -> (numpy type, multiplier the stored integer is read with)
DF_TYPES = {
    'b': ('i1', None), 'B': ('u1', None), 'h': ('<i2', None), 'H': ('<u2', None),
    'i': ('<i4', None), 'I': ('<u4', None), 'f': ('<f4', None), 'd': ('<f8', None),
    'n': ('S4', None), 'N': ('S16', None), 'Z': ('S64', None), 'c': ('<i2', 0.01),
    'C': ('<u2', 0.01), 'e': ('<i4', 0.01), 'E': ('<u4', 0.01), 'L': ('<i4', 1e-7),
    'M': ('u1', None), 'q': ('<i8', None), 'Q': ('<u8', None),
}

#: the message formats of ArduPilot 4.x used by the tests (name: (format, columns))
AP4 = {
    'PARM': ('QNf', 'TimeUS,Name,Value'),
    'MSG': ('QZ', 'TimeUS,Message'),
    'MAG': ('QBhhhhhhhhhBI', 'TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S'),
    'XKQ': ('QBffff', 'TimeUS,C,Q1,Q2,Q3,Q4'),
    'ATT': ('QccccCCCCB', 'TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF'),
    'BAT': ('QBfffffcf', 'TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res'),
    'CTUN': ('Qfff', 'TimeUS,ThI,ThO,ThH'),
    'RCOU': ('QHHHHHHHHHHHHHH', 'TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14'),
    'GPS': ('QBBIHBcLLeffffB', 'TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,'
            'Yaw,U'),
    'IMU': ('QBffffffIIfBBHH', 'TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz'),
    'ESC': ('QBeffcfcf', 'TimeUS,Instance,RPM,RawRPM,Volt,Curr,Temp,CTot,MotTemp,Err'),
}
#: ArduPilot 3.5's per-instance compass messages (no instance field, old names)
AP35 = {
    'PARM': AP4['PARM'], 'MSG': AP4['MSG'],
    'MAG': ('QhhhhhhhhhBI', 'TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S'),
    'MAG2': ('QhhhhhhhhhBI', 'TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S'),
    'NKQ1': ('Qffff', 'TimeUS,Q1,Q2,Q3,Q4'),
}


class DataFlash:
    """A DataFlash log built in memory: ``define`` the types, ``write`` columns, ``save``."""

    def __init__(self, formats=AP4):
        self.buf = bytearray(b'\xa3\x95\x80' + struct.pack(
            '<BB4s16s64s', 128, 89, b'FMT', b'BBnNZ', b'Type,Length,Name,Format,Columns'))
        self.types = {}
        for name, (fmt, cols) in formats.items():
            self.define(name, fmt, cols)

    def define(self, name, fmt, columns):
        """Write the FMT message of a new type."""
        tid = 129 + len(self.types)
        fields = columns.split(',')
        dtype = np.dtype([('h1', 'u1'), ('h2', 'u1'), ('type', 'u1')] +
                         [(c, DF_TYPES[ch][0]) for c, ch in zip(fields, fmt)])
        self.types[name] = (tid, dtype, fmt, fields)
        self.buf += b'\xa3\x95\x80' + struct.pack(
            '<BB4s16s64s', tid, dtype.itemsize, name.encode(), fmt.encode(), columns.encode())

    def write(self, name, **columns):
        """
        Append M messages of type ``name``: each column an (M,) array in the reader's units.

        Values of the scaled integer types (c, C, e, E, L) are divided by their multiplier
        and rounded; the other integer types are rounded.
        """
        tid, dtype, fmt, fields = self.types[name]
        m = len(np.atleast_1d(next(iter(columns.values()))))
        rec = np.zeros(m, dtype)
        rec['h1'], rec['h2'], rec['type'] = 0xA3, 0x95, tid
        for col, ch in zip(fields, fmt):
            if col not in columns:
                continue
            v = columns[col]
            np_t, mult = DF_TYPES[ch]
            if np.dtype(np_t).kind == 'S':
                rec[col] = [s.encode() if isinstance(s, str) else s
                            for s in np.broadcast_to(np.asarray(v, object), (m,))]
                continue
            v = np.asarray(v, float)
            if mult:
                v = v / mult
            if np.dtype(np_t).kind in 'iu':
                v = np.round(v)
            rec[col] = v
        self.buf += rec.tobytes()

    def params(self, values, t_us=1000):
        """Append PARM messages {name: value} at time ``t_us``."""
        names = list(values)
        self.write('PARM', TimeUS=np.full(len(names), t_us), Name=names,
                   Value=[values[n] for n in names])

    def save(self, path):
        """Write the log to ``path``; return the path."""
        with open(path, 'wb') as fh:
            fh.write(bytes(self.buf))
        return path


def write_text_dataflash(path, messages, formats=AP4):
    """
    Write a text DataFlash log: ``messages`` [(name, {column: value})] in order.

    Lines ``FMT, type, length, name, format, columns`` then ``NAME, v1, v2, ...`` (the
    values as the reader gives them: degrees, not centidegrees).
    """
    lines = []
    ids = {}
    for name, (fmt, cols) in formats.items():
        ids[name] = 129 + len(ids)
        size = 3 + sum(np.dtype(DF_TYPES[ch][0]).itemsize for ch in fmt)
        lines.append(f'FMT, {ids[name]}, {size}, {name}, {fmt}, {cols}')
    for name, row in messages:
        cols = formats[name][1].split(',')
        lines.append(', '.join([name] + [str(row.get(c, 0)) for c in cols]))
    with open(path, 'w') as fh:
        fh.write('\n'.join(lines) + '\n')
    return path


# -- ULog ---------------------------------------------------------------------------------

_ULOG_TYPES = {'uint64_t': 'Q', 'int64_t': 'q', 'uint32_t': 'I', 'int32_t': 'i',
               'uint16_t': 'H', 'int16_t': 'h', 'uint8_t': 'B', 'int8_t': 'b', 'float': 'f',
               'double': 'd', 'bool': '?', 'char': 'c'}


class ULog:
    """
    A ULog file built in memory.

    ``topic(name, fields)`` declares a format (fields [(type, name)], ``timestamp`` first,
    arrays as ``float[4]``); ``info``, ``param`` add definitions; ``data(name, multi_id,
    columns)`` appends the messages of one subscription (columns: (M,) arrays; an array
    field as (M, k)).
    """

    def __init__(self, version=1, start_us=0):
        self.header = b'ULog\x01\x12\x35' + struct.pack('<BQ', version, start_us)
        self.defs = bytearray()
        self.body = bytearray()
        self.formats = {}
        self.subs = {}

    @staticmethod
    def _msg(kind, payload):
        return struct.pack('<HB', len(payload), ord(kind)) + payload

    def topic(self, name, fields):
        """Declare the format of topic ``name``."""
        text = name + ':' + ''.join(f'{t} {n};' for t, n in fields)
        self.defs += self._msg('F', text.encode())
        dt = []
        for t, n in fields:
            base, _, count = t.partition('[')
            code = np.dtype('<' + _ULOG_TYPES[base]) if base != 'char' else np.dtype('S1')
            dt.append((n, code, (int(count[:-1]),)) if count else (n, code))
        self.formats[name] = np.dtype(dt)

    def info(self, key, value):
        """Add an information message (a string value)."""
        v = value.encode()
        k = f'char[{len(v)}] {key}'.encode()
        self.defs += self._msg('I', struct.pack('<B', len(k)) + k + v)

    def param(self, name, value):
        """Add a parameter: an int is int32_t, anything else float."""
        if isinstance(value, int):
            k, v = f'int32_t {name}'.encode(), struct.pack('<i', value)
        else:
            k, v = f'float {name}'.encode(), struct.pack('<f', value)
        self.defs += self._msg('P', struct.pack('<B', len(k)) + k + v)

    def data(self, name, multi_id, **columns):
        """Append the messages of topic ``name`` instance ``multi_id``."""
        key = (name, multi_id)
        if key not in self.subs:
            self.subs[key] = len(self.subs)
            self.body += self._msg('A', struct.pack('<BH', multi_id, self.subs[key]) +
                                   name.encode())
        dt = self.formats[name]
        m = len(columns['timestamp'])
        rec = np.zeros(m, dt)
        for col, v in columns.items():
            rec[col] = v
        size = dt.itemsize + 2
        out = np.zeros(m, np.dtype([('size', '<u2'), ('type', 'u1'), ('id', '<u2'),
                                    ('rec', dt)]))
        out['size'], out['type'], out['id'], out['rec'] = size, ord('D'), self.subs[key], rec
        self.body += out.tobytes()

    def save(self, path):
        """Write the file; return the path."""
        with open(path, 'wb') as fh:
            fh.write(self.header + bytes(self.defs) + bytes(self.body))
        return path


SENSOR_MAG = [('uint64_t', 'timestamp'), ('uint64_t', 'timestamp_sample'),
              ('uint32_t', 'device_id'), ('float', 'x'), ('float', 'y'), ('float', 'z'),
              ('float', 'temperature'), ('uint32_t', 'error_count'), ('bool', 'is_external')]
VEHICLE_MAGNETOMETER = [('uint64_t', 'timestamp'), ('uint64_t', 'timestamp_sample'),
                        ('uint32_t', 'device_id'), ('float[3]', 'magnetometer_ga'),
                        ('uint8_t', 'calibration_count')]
VEHICLE_ATTITUDE = [('uint64_t', 'timestamp'), ('uint64_t', 'timestamp_sample'),
                    ('float[4]', 'q')]
BATTERY_STATUS = [('uint64_t', 'timestamp'), ('float', 'voltage_v'), ('float', 'current_a'),
                  ('float', 'temperature')]
ACTUATOR_MOTORS = [('uint64_t', 'timestamp'), ('float[4]', 'control')]
ACTUATOR_CONTROLS = [('uint64_t', 'timestamp'), ('float[8]', 'control')]
SENSOR_GPS = [('uint64_t', 'timestamp'), ('double', 'latitude_deg'), ('double', 'longitude_deg'),
              ('double', 'altitude_msl_m'), ('uint64_t', 'time_utc_usec'),
              ('uint8_t', 'fix_type')]
