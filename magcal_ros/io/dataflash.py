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
ArduPilot DataFlash logs (``.bin``, text ``.log``) -> :class:`~.vehicle_base.VehicleLog`.

pymavlink's DFReader opens and indexes the log; a binary log's messages of one type are then
decoded at once through a numpy dtype built from the type's FMT (DFReader's
``FORMAT_TO_STRUCT``); a text log is read through ``recv_match`` (slow).

The compass (``MAG``) is logged in mG in the body frame after AP_Compass's ``correct_field``
(AP_Compass_Backend.cpp; pymavlink's tools/magfit_WMM.py); :func:`ardupilot_raw` undoes it
(docs/design.md §1, "Vehicle logs", which also names the attitude chosen).  Old logs (before
3.4: TimeMS, PARM and MSG without time, CURR in centiamps, RCOU ``Ch1``..) are read too.
"""
import datetime
import mmap
import re

from magcal_ros.io.vehicle_base import gps_site, NT_PER_MGAUSS, SLOW_RATE_HZ, Stream, \
    VehicleLog, VehicleLogError
import numpy as np

#: messages gathered at a time (bounds the index array: rows x message length x 8 bytes)
_BLOCK = 65536
#: COMPASS_SCALE is applied only inside these bounds (AP_Compass have_scale_factor)
SCALE_BOUNDS = (0.85, 1.4)
#: GPS time: week 0 starts on 1980-01-06
_GPS_EPOCH = datetime.datetime(1980, 1, 6)
_INSTANCE = ('I', 'Inst', 'Instance')
#: the message types the reader may read (their index is kept; DFReader's is dropped)
_TYPES = re.compile(r'(MAG\d?|XKQ\d?|NKQ\d?|ATT|GPS\d?|BAT\d?|CURR|CTUN|RCOU|RCO2|RCO3|'
                    r'ESC\d?|IMU\d?|BARO|BAR\d|POWR|MSG|PARM)')
#: the fields the reader uses (the others are not decoded)
_FIELDS = re.compile(r'(TimeUS|TimeMS|T|Week|I|Inst|Instance|C|Mag[XYZ]|Ofs[XYZ]|MO[XYZ]|'
                     r'MOfs[XYZ]|Health|Q[1-4]|Roll|Pitch|Yaw|Status|GWk|GMS|Lat|Lng|Alt|Curr|'
                     r'Volt|Temp|ThO|ThrOut|RPM|Vcc|Name|Value|Message|(C|Ch|Chan)\d+)')


class _Log:
    """A DataFlash log opened by DFReader; ``table(name)`` decodes one message type."""

    def __init__(self, path, text):
        from pymavlink import DFReader
        self.path = path
        self.text = text
        try:
            self.r = (DFReader.DFReader_text if text else DFReader.DFReader_binary)(path)
        except Exception as exc:           # DFReader raises anything on a damaged file
            raise VehicleLogError(
                f'{path}: cannot read this DataFlash log ({type(exc).__name__}: {exc}): the '
                'file is damaged or not a DataFlash log; download it from the autopilot '
                'again') from None
        self.by_name = (dict(self.r.formats) if text else
                        {f.name: f for f in self.r.formats.values()})
        if 'FMT' not in self.by_name or (not text and int(self.r.counts[0x80]) == 0):
            raise VehicleLogError(f'{path}: no FMT message: not a DataFlash log, or its start '
                                  'is missing; download it from the autopilot again')
        self._params = None
        if not text:
            # DFReader's index (a list per type): only the types read, as int64 arrays
            self.offsets = {f.type: np.asarray(self.r.offsets[f.type], np.int64)
                            for f in self.by_name.values()
                            if _TYPES.fullmatch(f.name) and self.r.counts[f.type]}
            self.r.offsets = None
            self._release()

    def _release(self):
        """Drop the file's pages from this process's memory (they are read again if needed)."""
        if hasattr(self.r.data_map, 'madvise'):
            self.r.data_map.madvise(mmap.MADV_DONTNEED)

    def close(self):
        """Release the file."""
        self.r.close()

    def count(self, name):
        """Return the number of messages of type ``name``."""
        if self.text:
            return int(self.r.counts.get(name, 0))
        tid = self.r.name_to_id.get(name)
        return 0 if tid is None or tid not in self.offsets else len(self.offsets[tid])

    def columns(self, name):
        """Return the column names of type ``name`` (empty when the log does not define it)."""
        f = self.by_name.get(name)
        return list(f.columns) if f is not None else []

    def table(self, name, every=1):
        """
        Return {column: (M,) array} of every ``every``-th message of type ``name``, or None.

        Numbers float64 (the format's multiplier applied), strings str; ``t`` the time, s.
        """
        if self.count(name) == 0:
            return None
        cols = self._text_table(name, every) if self.text else self._binary_table(name, every)
        n = len(next(iter(cols.values()))) if cols else 0
        if 'TimeUS' in cols:
            cols['t'] = cols['TimeUS'] * 1e-6
        elif 'T' in cols and 'Week' in cols:
            cols['t'] = cols['T'] * 1e-3            # old GPS: TimeMS is the GPS time of week
        elif 'TimeMS' in cols:
            cols['t'] = cols['TimeMS'] * 1e-3
        elif name in ('PARM', 'MSG'):
            cols['t'] = np.zeros(n)                 # old logs: written at start-up
        else:
            raise VehicleLogError(f'{self.path}: message {name} has no TimeUS or TimeMS field: '
                                  'this DataFlash version is not supported')
        return cols

    def _binary_table(self, name, every):
        from pymavlink.DFReader import FORMAT_TO_STRUCT
        fmt = self.by_name[name]
        names, formats, mults = [], [], {}
        for col, ch in zip(fmt.columns, fmt.format):
            if ch not in FORMAT_TO_STRUCT:
                raise VehicleLogError(f'{self.path}: message {name}: unknown format character '
                                      f'{ch!r}: this DataFlash version is not supported')
            code, mult, _ = FORMAT_TO_STRUCT[ch]          # struct's code: numpy's, packed
            np_t = 'S' + code[:-1] if code.endswith('s') else '<' + code
            if col in names:
                col = f'{col}_{len(names)}'
            names.append(col)
            formats.append(np_t)
            if mult:
                mults[col] = mult
        dtype = np.dtype({'names': names, 'formats': formats})      # packed, as the log
        length = fmt.len - 3
        if dtype.itemsize != length:
            raise VehicleLogError(f'{self.path}: message {name}: its FMT says {fmt.len} bytes '
                                  f'but its format {fmt.format!r} makes {dtype.itemsize + 3}: '
                                  'the log is damaged')
        wanted = [c for c in names if _FIELDS.fullmatch(c)]
        buf = np.frombuffer(self.r.data_map, np.uint8)
        try:
            ofs = self.offsets[fmt.type][::every] + 3
            ofs = ofs[ofs + length <= len(buf)]
            m = len(ofs)
            out = {c: np.empty(m, float if dtype[c].kind != 'S' else dtype[c])
                   for c in wanted}
            ar = np.arange(length)
            for a in range(0, m, _BLOCK):
                rec = buf[ofs[a:a + _BLOCK, None] + ar].view(dtype)[:, 0]
                for c in wanted:
                    out[c][a:a + _BLOCK] = rec[c]
        finally:
            del buf
        self._release()
        for c in wanted:
            if out[c].dtype.kind == 'S':
                out[c] = np.char.decode(np.char.rstrip(out[c], b'\0'), 'ascii', 'replace')
            elif c in mults:
                out[c] *= mults[c]
        return out

    def _text_table(self, name, every):
        self.r.rewind()
        rows = [m.to_dict() for m in iter(lambda: self.r.recv_match(type=name), None)][::every]
        out = {}
        for col in self.columns(name):
            if not _FIELDS.fullmatch(col):
                continue
            vals = [row.get(col) for row in rows]
            try:
                out[col] = np.array(vals, float)
            except (TypeError, ValueError):
                out[col] = np.array([str(v) for v in vals])
        return out

    def params(self):
        """Return {name: (times (K,) s, values (K,))} of the PARM messages, in time order."""
        if self._params is None:
            self._params = {}
            tab = self.table('PARM')
            if tab is not None:
                order = np.argsort(tab['t'], kind='stable')
                names = tab['Name'][order]
                t, v = tab['t'][order], tab['Value'][order]
                self._params = {str(n): (t[sel], v[sel])
                                for n in np.unique(names) for sel in [names == n]}
        return self._params

    def param(self, name, default=None):
        """Return the first value of parameter ``name`` in the log, or ``default``."""
        p = self.params().get(name)
        return default if p is None else float(p[1][0])

    def param_at(self, name, t, default):
        """(M,) value of parameter ``name`` at times ``t`` (the last PARM before each)."""
        p = self.params().get(name)
        if p is None:
            return np.full(len(t), float(default))
        i = np.searchsorted(p[0], t, side='right') - 1
        return p[1][np.clip(i, 0, len(p[1]) - 1)]


def ardupilot_raw(field, offsets, motor, diag, offdiag, scale, motor_first=False):
    """
    Return the raw body-frame reading r from ArduPilot's F = M s (r + o) + m, any unit.

    ``field`` (N, 3) the logged F (MAG.MagX..); ``offsets``, ``motor`` (N, 3) o and m as
    logged (OfsX.., MOX..); ``diag``, ``offdiag`` (N, 3) or (3,) COMPASS_DIA (all zero read
    as 1) and COMPASS_ODI (xy, xz, yz), M; ``scale`` (N,) or scalar COMPASS_SCALE s, 1
    outside :data:`SCALE_BOUNDS`; ``motor_first``: firmware before 3.6, F = M (r + o + m).
    Returns (N, 3) r = M^-1 (F - m) / s - o (older: M^-1 F - o - m).
    """
    field = np.asarray(field, float)
    n = len(field)
    d = np.broadcast_to(np.asarray(diag, float), (n, 3)).copy()
    d[(d == 0).all(axis=1)] = 1.0
    od = np.broadcast_to(np.asarray(offdiag, float), (n, 3))
    mat = np.stack([d[:, 0], od[:, 0], od[:, 1], od[:, 0], d[:, 1], od[:, 2],
                    od[:, 1], od[:, 2], d[:, 2]], axis=-1).reshape(n, 3, 3)
    s = np.broadcast_to(np.asarray(scale, float), (n,)).copy()
    s[~((s >= SCALE_BOUNDS[0]) & (s <= SCALE_BOUNDS[1]))] = 1.0
    o = np.asarray(offsets, float)
    m = np.asarray(motor, float)
    if motor_first:
        return np.linalg.solve(mat, field[..., None])[..., 0] - o - m
    return np.linalg.solve(mat, (field - m)[..., None])[..., 0] / s[:, None] - o


def _pname(log, kind, k, axis=''):
    """Name in the log of compass ``k``'s parameter (COMPASS_OFS2_X or COMPASS2_OFS_X)."""
    suffix = f'_{axis}' if axis else ''
    other = 'EXTERN' if kind == 'EXTERNAL' else kind
    names = [f'COMPASS_{kind}{suffix}' if k == 1 else f'COMPASS_{other}{k}{suffix}',
             f'COMPASS{k}_{kind}{suffix}']
    params = log.params()
    return next((n for n in names if n in params), names[0])


def _split(log, name, every=1, older='{name}{k}'):
    """[(instance 0.., table)] of message ``name`` by its instance field, else NAME, NAME2..."""
    tab = log.table(name, every)
    if tab is None:
        return []
    inst = next((c for c in _INSTANCE if c in tab), None)
    if inst is not None:
        return [(k, {c: v[sel] for c, v in tab.items()})
                for k in np.unique(tab[inst]).astype(int).tolist() for sel in [tab[inst] == k]]
    out = [(0, tab)]
    for k in range(2, 9):
        other = log.table(older.format(name=name, k=k), every)
        if other is None:
            break
        out.append((k - 1, other))
    return out


def _firmware(log):
    """Return (vehicle name, (major, minor)) from the log's MSG texts, or (None, None)."""
    tab = log.table('MSG')
    if tab is None:
        return None, None
    for text in tab['Message'].tolist():
        m = re.search(r'\b(Ardu\w+|APM:\w+|Rover|Blimp|AntennaTracker|AP_Periph)\s+'
                      r'V(\d+)\.(\d+)', str(text))
        if m:
            name = m.group(1)
            if name.startswith('APM:'):             # 'APM:Copter V3.3' (before 3.4)
                name = {'Copter': 'ArduCopter', 'Plane': 'ArduPlane', 'Rover': 'ArduRover'}.get(
                    name[4:], name[4:])
            return name, (int(m.group(2)), int(m.group(3)))
    return None, None


def read_dataflash(path, text=False):
    """Read an ArduPilot DataFlash log (``text``: a text ``.log``) into a VehicleLog."""
    log = _Log(path, text)
    try:
        return _read(log, path, text)
    finally:
        log.close()


def _read(log, path, text):
    vehicle, version = _firmware(log)
    out = VehicleLog('ArduPilot DataFlash (text)' if text else 'ArduPilot DataFlash')
    if vehicle:
        out.info['vehicle'] = vehicle
        out.info['firmware'] = f'{vehicle} V{version[0]}.{version[1]}'
    motor_first = version is not None and version < (3, 6)
    mags = _split(log, 'MAG')
    span = None
    for k, tab in mags:
        j = k + 1
        t = tab['t']
        if span is None and len(t) > 1:
            span = (float(t.min()), float(t.max()))
        f = np.column_stack([tab['MagX'], tab['MagY'], tab['MagZ']])
        o = np.column_stack([tab.get(f'Ofs{a}', np.zeros(len(t))) for a in 'XYZ'])
        mo_cols = [next((c for c in (f'MO{a}', f'MOfs{a}') if c in tab), None) for a in 'XYZ']
        motct = log.param('COMPASS_MOTCT', 0.0)
        if None in mo_cols:
            mo = np.zeros((len(t), 3))
            if motct or log.param('COMPASS_PMOT_EN', 0.0):
                out.warnings.append(f'compass {j}: the log has no motor offsets (MOX..) though '
                                    'motor compensation is on: it is not undone')
        else:
            mo = np.column_stack([tab[c] for c in mo_cols])
        ofs_p = np.column_stack([log.param_at(_pname(log, 'OFS', j, a), t, np.nan)
                                 for a in 'XYZ'])
        if len(t) and np.isfinite(ofs_p[0]).all() and np.abs(ofs_p[0] - o[0]).max() > 1.0:
            # the parameters read as compass j's are another compass's
            logged = ', '.join(f'{x:.0f}' for x in o[0])
            param = ', '.join(f'{x:.0f}' for x in ofs_p[0])
            out.warnings.append(
                f"compass {j}: its logged offsets ({logged} mG) are not its parameters' "
                f'({param} mG): the soft-iron and scale parameters undone may be another '
                "compass's")
        dia = np.column_stack([log.param_at(_pname(log, 'DIA', j, a), t, 1.0) for a in 'XYZ'])
        odi = np.column_stack([log.param_at(_pname(log, 'ODI', j, a), t, 0.0) for a in 'XYZ'])
        scale = log.param_at(_pname(log, 'SCALE', j), t, 0.0)
        raw = ardupilot_raw(f, o, mo, dia, odi, scale, motor_first) * NT_PER_MGAUSS
        name = 'MAG' if 'I' in tab or j == 1 else f'MAG{j}'
        out.compasses.append(Stream(t, raw, f'{name} instance {k}'))
        out.compass_temps.append(None)
        out.onboard.append(_onboard(log, j, tab, motct))
    duration = (span[1] - span[0]) if span else None
    _attitude(log, out)
    _gps(log, out)
    _aux(log, out, vehicle, duration)
    return out


def _onboard(log, j, tab, motct):
    """Return the onboard calibration of compass ``j`` as the log's parameters say (nT)."""
    def vec(kind, default):
        return [log.param(_pname(log, kind, j, a), default) for a in 'XYZ']

    def number(kind):
        v = log.param(_pname(log, kind, j))
        return None if v is None else int(v)
    scale = log.param(_pname(log, 'SCALE', j), 0.0)
    prio = log.param(f'COMPASS_PRIO{j}_ID')
    dev = prio if prio is not None else log.param(_pname(log, 'DEV_ID', j))
    types = {0: 'none', 1: 'throttle', 2: 'current'}
    pmot = bool(log.param('COMPASS_PMOT_EN', 0.0)) and j == 1
    dia = vec('DIA', 1.0)
    out = {
        'compass': j, 'autopilot': 'ArduPilot',
        'device_id': None if dev is None else int(dev),
        'external': number('EXTERNAL'), 'orientation': number('ORIENT'),
        'offsets_nt': [x * NT_PER_MGAUSS for x in vec('OFS', 0.0)],
        'diagonals': [1.0, 1.0, 1.0] if all(x == 0 for x in dia) else dia,
        'offdiagonals': vec('ODI', 0.0),
        'scale': scale,
        'scale_applied': SCALE_BOUNDS[0] <= scale <= SCALE_BOUNDS[1],
        'motor_compensation': {
            'type': 'per-motor' if pmot else types.get(int(motct), f'unknown ({motct})'),
            'vector_nt_per_unit': [x * NT_PER_MGAUSS for x in vec('MOT', 0.0)],
            'unit': {1: 'nT per unit throttle (0..1)', 2: 'nT per A'}.get(int(motct), '')},
    }
    if 'OfsX' in tab and len(tab['OfsX']):
        logged = np.column_stack([tab[f'Ofs{a}'] for a in 'XYZ'])
        if np.ptp(logged, axis=0).max() > 0:
            out['offsets_changed_in_log'] = True
    return out


#: an EKF core is used only within this of ATT (median, deg): ATT is what the AHRS used
EKF_ATT_AGREEMENT_DEG = 2.0


def _att_attitude(log):
    """Return (t (M,) s, (M, 4) autopilot-body quaternions) of ATT, AHRS_TRIM removed."""
    tab = log.table('ATT')
    if tab is None:
        return None
    from scipy.spatial.transform import Rotation
    q = Rotation.from_euler('ZYX', np.column_stack([tab['Yaw'], tab['Pitch'], tab['Roll']]),
                            degrees=True).as_quat(scalar_first=True)
    trim = [log.param(f'AHRS_TRIM_{a}', 0.0) for a in 'XYZ']
    r = Rotation.from_quat(q, scalar_first=True) * Rotation.from_euler(
        'ZYX', [trim[2], trim[1], trim[0]])
    return tab['t'], r.as_quat(scalar_first=True)


def _ekf_attitudes(log):
    """
    Return [(t, (M, 4) quaternions, source)] of the EKF's cores (XKQ or NKQ), or [].

    The EKF AHRS_EKF_TYPE selects (else EKF3), its primary core first; old logs: XKQ1/NKQ1.
    """
    ekf = log.param('AHRS_EKF_TYPE')
    order = [('XKQ', 'EKF3', 'EK3_PRIMARY'), ('NKQ', 'EKF2', 'EK2_PRIMARY')]
    if ekf == 2:
        order.reverse()
    for name, label, primary in order:
        tab = log.table(name) if log.count(name) else log.table(f'{name}1')
        if tab is None:
            continue
        q = np.column_stack([tab[f'Q{i}'] for i in range(1, 5)])
        if 'C' not in tab:
            return [(tab['t'], q, f'ArduPilot {label} {name}1 core 0')]
        first = int(log.param(primary, 0.0))
        cores = sorted(np.unique(tab['C']).astype(int).tolist(), key=lambda c: c != first)
        return [(tab['t'][sel], q[sel], f'ArduPilot {label} {name} core {core}')
                for core in cores for sel in [tab['C'] == core]]
    return []


def _disagreement_deg(ekf, att):
    """Median angle (deg) between an EKF core's attitude and ATT's, or None (no overlap)."""
    from magcal_ros.core.geometry.attitude import interpolate
    t, q, _ = ekf
    norm = np.linalg.norm(q, axis=1)
    ok = (t >= att[0].min()) & (t <= att[0].max()) & (np.abs(norm - 1) < 1e-3)
    if ok.sum() < 2:
        return None
    qa = interpolate(att[0], att[1], t[ok])
    dot = np.abs(np.einsum('ij,ij->i', q[ok] / norm[ok, None], qa))
    return float(np.degrees(np.median(2 * np.arccos(np.clip(dot, -1, 1)))))


def _attitude(log, out):
    """
    Set the log's attitude: the EKF core closest to ATT within :data:`EKF_ATT_AGREEMENT_DEG`.

    None within it: ATT itself (with a warning); without ATT, the primary core.
    """
    cores = _ekf_attitudes(log)
    att = _att_attitude(log)
    att_src = 'ArduPilot ATT (roll, pitch, yaw; AHRS_TRIM removed)'
    chosen = cores[0] if cores else None
    if cores and att is not None:
        angles = [_disagreement_deg(c, att) for c in cores]
        known = [(a, k) for k, a in enumerate(angles) if a is not None]
        if known:
            best, k = min(known)
            chosen = cores[k] if best <= EKF_ATT_AGREEMENT_DEG else None
            if chosen is None:
                out.warnings.append(
                    f'{cores[k][2]} differs from ATT by {best:.1f} deg (median; the other '
                    'cores more): the AHRS was not using the EKF (DCM); the attitude is '
                    'taken from ATT')
    if chosen is not None:
        out.attitude = Stream(chosen[0], chosen[1], chosen[2])
        out.attitude_source = chosen[2]
    elif att is not None:
        out.attitude = Stream(att[0], att[1], att_src)
        out.attitude_source = att_src


def _gps(log, out):
    parts = _split(log, 'GPS')
    if not parts:
        return
    tab = parts[0][1]
    week = tab.get('GWk', tab.get('Week'))
    ms = tab.get('GMS', tab.get('TimeMS') if 'Week' in tab else None)
    good = tab['Status'] >= 3
    if week is None or ms is None or not good.any():
        return
    dates = [(_GPS_EPOCH + datetime.timedelta(weeks=float(w), milliseconds=float(s)))
             .strftime('%Y-%m-%d') if w > 0 else '' for w, s in zip(week[good], ms[good])]
    out.gps = gps_site(tab['Lat'][good], tab['Lng'][good], tab['Alt'][good], dates)


def _every(log, name, duration):
    """Read every k-th message of a fast stream so that it is read at ~SLOW_RATE_HZ."""
    return max(1, int(log.count(name) / (duration * SLOW_RATE_HZ))) if duration else 1


def _aux(log, out, vehicle, duration):
    # batteries
    bats = _split(log, 'BAT')
    for k, tab in bats:
        tag = 'battery' if k == 0 else f'battery{k + 1}'
        for col, what, unit in (('Curr', 'current', 'A'), ('Volt', 'voltage', 'V'),
                                ('Temp', 'temp', 'degC')):
            if col in tab and (col != 'Temp' or np.any(tab[col] != 0)):
                out.add_aux(f'aux_{tag}_{what}', tab['t'], tab[col], unit, f'BAT[{k}].{col}')
    if not bats:
        tab = log.table('CURR')
        if tab is not None:
            fmt = log.by_name['CURR']
            ints = {c: ch in 'hHiI' for c, ch in zip(fmt.columns, fmt.format)}
            for col, name, unit in (('Curr', 'aux_battery_current', 'A'),
                                    ('Volt', 'aux_battery_voltage', 'V')):
                if col in tab:
                    v = tab[col] / 100.0 if ints.get(col) else tab[col]
                    out.add_aux(name, tab['t'], v, unit, f'CURR.{col}')
    # throttle
    tab = log.table('CTUN')
    if tab is not None and vehicle:
        col = next((c for c in ('ThO', 'ThrOut') if c in tab), None)
        div = None
        if vehicle in ('ArduCopter', 'ArduSub') or 'Heli' in vehicle:
            div = 1.0 if col == 'ThO' else 1000.0
        elif vehicle == 'ArduPlane':
            div = 100.0
        if col is not None and div is not None:
            out.add_aux('aux_throttle', tab['t'], tab[col] / div, '0..1', f'CTUN.{col}')
    # motors: the outputs whose SERVOn_FUNCTION is a motor
    motors = {}
    for n in range(1, 33):
        f = log.param(f'SERVO{n}_FUNCTION', log.param(f'RC{n}_FUNCTION'))
        if f is not None and (33 <= int(f) <= 40 or 82 <= int(f) <= 85):
            motors[n] = int(f) - (32 if int(f) <= 40 else 73)      # Motor1..8, Motor9..12
    if not motors and vehicle == 'ArduCopter':
        # Copter 3.4 and older: outputs 1..n of the frame named at start-up ('Frame: QUAD')
        tab = log.table('MSG')
        texts = tab['Message'] if tab is not None else []
        found = [re.search(r'Frame: (\w+)', str(x)) for x in texts]
        frame = next((m.group(1) for m in found if m), None)
        count = {'QUAD': 4, 'HEXA': 6, 'OCTA': 8, 'OCTA_QUAD': 8, 'Y6': 6, 'TRI': 3,
                 'DODECA_HEXA': 12}.get(frame, 0)
        motors = {n: n for n in range(1, count + 1)}
    tables = {}
    for n, k in sorted(motors.items()):
        msg = 'RCOU' if n <= 14 else ('RCO2' if n <= 18 else 'RCO3')
        if msg not in tables:
            tables[msg] = log.table(msg)
        tab = tables[msg]
        col = next((c for c in (f'C{n}', f'Ch{n}', f'Chan{n}') if tab is not None and c in tab),
                   None)
        if col is not None:
            out.add_aux(f'aux_motor{k}', tab['t'], tab[col], 'PWM us', f'{msg}.{col}')
    # ESCs: ESC with an instance field, or ESC1..ESC8 in older logs
    escs = (_split(log, 'ESC') if log.count('ESC') else
            [(k - 1, log.table(f'ESC{k}')) for k in range(1, 9) if log.count(f'ESC{k}')])
    for k, tab in escs:
        for col, what, unit in (('Curr', 'current', 'A'), ('RPM', 'rpm', 'rpm'),
                                ('Temp', 'temp', 'degC')):
            if col in tab:
                out.add_aux(f'aux_esc{k + 1}_{what}', tab['t'], tab[col], unit,
                            f'ESC[{k}].{col}')
    # temperatures and the board's voltage (slow: read at ~SLOW_RATE_HZ)
    for name, older, tag, cols in (('IMU', '{name}{k}', 'imu', ('T', 'Temp')),
                                   ('BARO', 'BAR{k}', 'baro', ('Temp',))):
        for k, tab in _split(log, name, _every(log, name, duration), older):
            col = next((c for c in cols if c in tab), None)
            if col is not None:
                out.add_aux(f'aux_{tag}_temp' if k == 0 else f'aux_{tag}{k + 1}_temp',
                            tab['t'], tab[col], 'degC', f'{name}[{k}].{col}')
    tab = log.table('POWR', _every(log, 'POWR', duration))
    if tab is not None and 'Vcc' in tab:
        out.add_aux('aux_board_voltage', tab['t'], tab['Vcc'], 'V', 'POWR.Vcc')
