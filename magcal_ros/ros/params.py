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
ROS parameter declaration and validation of the nodes.

Every parameter is declared from a :class:`ParamSpec` (name, default, description with the
unit, validator): ``ros2 param describe`` and the ``add_on_set_parameters_callback`` check
come from one table. The settings dataclasses (:class:`CalibrationSettings`,
:class:`CorrectorSettings`) keep the code doing the work away from a ``Node``.
"""
from dataclasses import dataclass, fields, make_dataclass
import math
import os

from magcal_ros.core import effects as fx
from magcal_ros.core.model import Model
import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.parameter import Parameter


def ros_home():
    """``$ROS_HOME``, or ``~/.ros`` when it is unset (as ROS 2 resolves its log directory)."""
    return os.path.expanduser(os.environ.get('ROS_HOME') or os.path.join('~', '.ros'))


def default_calibration_file():
    """Where both nodes read/write the active calibration unless told otherwise."""
    return os.path.join(ros_home(), 'magcal', 'calibration.yaml')


def default_report_dir():
    """Where calibration/diagnose writes its HTML report unless told otherwise."""
    return os.path.join(ros_home(), 'magcal', 'reports')


#: frame_id of corrected fields and of the gradient tensor (README: Frames)
DEFAULT_ARRAY_FRAME_ID = 'magcal_array'

#: the type of an array parameter of each ``item_type`` (an empty default has no items)
_ARRAY_TYPES = {str: Parameter.Type.STRING_ARRAY, float: Parameter.Type.DOUBLE_ARRAY,
                int: Parameter.Type.INTEGER_ARRAY}


@dataclass(frozen=True)
class ParamSpec:
    """
    One node parameter.

    ``default`` a bool, int, float, str, or a tuple (an array parameter of ``item_type``:
    ``str``, ``float`` or ``int``); ``description`` with its unit; ``check(value)`` returns
    the reason a value is refused, or None; ``read_only``: settable at start-up only;
    ``limits`` ``(lowest, highest)``, published as the descriptor's ``FloatingPointRange`` /
    ``IntegerRange``: rclpy refuses values outside it before ``check`` sees them (a range is
    the check of a number that has one).
    """

    name: str
    default: object
    description: str
    check: object = None
    read_only: bool = False
    item_type: type = str
    limits: tuple = None

    def descriptor(self):
        """Return the ``rcl_interfaces/ParameterDescriptor`` of this parameter."""
        ptype = (_ARRAY_TYPES[self.item_type] if isinstance(self.default, tuple)
                 else Parameter.Type.from_parameter_value(self.default))
        desc = ParameterDescriptor(name=self.name, type=ptype.value, description=self.description,
                                   read_only=self.read_only)
        if self.limits is not None and isinstance(self.default, float):
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(self.limits[0]), to_value=float(self.limits[1]), step=0.0)]
        elif self.limits is not None and isinstance(self.default, int):
            desc.integer_range = [IntegerRange(from_value=int(self.limits[0]),
                                               to_value=int(self.limits[1]), step=0)]
        return desc


def positive(unit):
    """Make a validator accepting a finite number > 0 (``unit`` is named in the refusal)."""
    def check(value):
        ok = isinstance(value, (int, float)) and math.isfinite(value) and value > 0
        return None if ok else f'must be a finite number > 0 {unit}, got {value!r}'
    return check


def non_empty_path(value):
    """Refuse an empty path string (returns the reason or None)."""
    return None if isinstance(value, str) and value.strip() else 'must be a non-empty path'


def topic_names(value):
    """Refuse names unusable as relative topic and column suffix (letters, digits, _)."""
    for name in value:
        if not name or not all(c.isalnum() or c == '_' for c in name) or name[0].isdigit():
            return (f'aux topic {name!r} is not a plain relative topic name (letters, digits and '
                    '_, not starting with a digit); it becomes the CSV column aux_<name>')
    if len(set(value)) != len(value):
        return f'aux topics must be unique, got {list(value)}'
    return None


def optional_topic(value):
    """Refuse a topic name ROS would reject ('' means none)."""
    if value and not all(c.isalnum() or c in '_/~' for c in value):
        return (f'{value!r} is not a topic name (letters, digits, _ and /); give e.g. '
                "'imu/data', or '' for none")
    return None


def positions_check(n_sensors):
    """Make a validator of ``sensor_positions_m``: empty, or 3 finite numbers per sensor."""
    def check(value):
        v = list(value)
        if v and (len(v) != 3 * n_sensors or not all(math.isfinite(x) for x in v)):
            return (f'must be empty (paper 004 cross for 4 sensors) or x y z per sensor in m: '
                    f'{3 * n_sensors} finite numbers for n_sensors {n_sensors}, got {len(v)}')
        return None
    return check


def input_topics_check(n_sensors):
    """Make a validator of ``input_topics``: empty, or one topic name per sensor."""
    def check(value):
        v = list(value)
        if not v:
            return None
        if len(v) != n_sensors:
            return (f'must name one sensor_msgs/MagneticField topic per sensor: {n_sensors} '
                    f'for n_sensors {n_sensors}, got {len(v)} ({v})')
        for name in v:
            if not name or optional_topic(name):
                return f'{name!r} is not a topic name (letters, digits, _ and /)'
        if len(set(v)) != len(v):
            return f'input topics must differ, got {v}'
        return None
    return check


def default_input_topics(n_sensors, given=()):
    """Return the input topic of each sensor: ``given``, or the driver's ``sensor{j}/raw``."""
    return tuple(given) if given else tuple(f'sensor{j}/raw' for j in range(1, n_sensors + 1))


def _degrees(kind, lo, hi):
    """Make a validator refusing ``kind`` outside ``lo``..``hi`` deg (NaN: not given)."""
    def check(value):
        if math.isnan(value) or lo <= value <= hi:
            return None
        return f'must be {kind} in {lo}..{hi} deg (or .nan: not given), got {value!r}'
    return check


latitude, longitude = _degrees('a latitude', -90, 90), _degrees('a longitude', -180, 360)


def iso_date(value):
    """Refuse a date that is neither '' nor YYYY-MM-DD."""
    import datetime
    if value:
        try:
            datetime.datetime.strptime(value, '%Y-%m-%d')
        except ValueError:
            return f"must be YYYY-MM-DD (or '' for the day of the calibration), got {value!r}"
    return None


def one_of(choices):
    """Make a validator accepting one of ``choices``."""
    def check(value):
        return None if value in choices else f'must be one of {list(choices)}, got {value!r}'
    return check


def frame_id(value):
    """Refuse a frame id tf2 cannot use: empty, a leading '/', or whitespace in it."""
    if not isinstance(value, str) or not value or value.startswith('/') or \
            any(c.isspace() for c in value):
        return (f'frame id {value!r} must be a non-empty name without a leading / or spaces '
                '(tf2 frame ids, REP 105)')
    return None


def module_paths(value):
    """Refuse plug-in references that are not ``package.module`` or ``package.module:Class``."""
    for ref in value:
        mod, _, attr = ref.partition(':')
        if not mod or not all(p.isidentifier() for p in mod.split('.')) or (
                attr and not attr.isidentifier()):
            return (f'plug-in {ref!r} is not a Python module path (package.module or '
                    'package.module:Class)')
    return None


def model_check(n_sensors):
    """Make a validator of a model (list of formula terms, docs/formulas.md): Model.from_spec."""
    def check(value):
        try:
            Model.from_spec(list(value), n_sensors)
        except ValueError as exc:
            return f'invalid model {list(value)}: {exc}'
        return None
    return check


def declare(node, specs):
    """Declare every parameter of ``specs`` on ``node``; return the specs by name (dict)."""
    for spec in specs:
        default = spec.default
        if isinstance(default, tuple):
            # an empty list would be typed BYTE_ARRAY: declare the type explicitly
            default = list(default) if default else _ARRAY_TYPES[spec.item_type]
        node.declare_parameter(spec.name, default, spec.descriptor())
    by_name = {s.name: s for s in specs}
    # values given at start-up (YAML, overrides) are checked like later changes
    given = (node.get_parameter_or(s.name) for s in specs)
    result = validate(by_name, [p for p in given if p.type_ != Parameter.Type.NOT_SET])
    if not result.successful:
        raise ValueError(f'bad parameter: {result.reason}')
    return by_name


def validate(specs, params):
    """
    Check the changes ``params`` against ``specs`` (by name): an on-set-parameters callback.

    Returns a ``SetParametersResult``, ``successful=False`` with the reason of the first
    refused value.
    """
    for p in params:
        spec = specs.get(p.name)
        if spec is None or spec.check is None:
            continue
        try:
            reason = spec.check(p.value)
        except Exception as exc:     # noqa: B902 -- a validator answers, it never ends spin
            reason = f'refused ({type(exc).__name__}: {exc})'
        if reason:
            return SetParametersResult(successful=False, reason=f'{p.name}: {reason}')
    return SetParametersResult(successful=True)


def value(node, name, default=None):
    """Return the value of a parameter (``default`` for an unset array parameter)."""
    p = node.get_parameter_or(name)
    return default if p.type_ == Parameter.Type.NOT_SET else p.value


# -- calibration node -----------------------------------------------------------------------
#: declared first: the model check of the other parameters depends on it
N_SENSORS = ParamSpec('n_sensors', 4, 'number of sensors of the array (topics sensor1/raw .. '
                      'sensor<S>/raw); count, read-only', read_only=True, limits=(1, 64))

#: declared and loaded before the model is checked; the only way a node imports effect code
PLUGINS = ParamSpec('plugins', (), 'effect plug-ins imported at start-up, each a module path '
                    'package.module (its MAGCAL_EFFECTS) or package.module:Class, as magcal '
                    '--plugin; read-only: no parameter write or message ever imports code',
                    module_paths, read_only=True, item_type=str)


def declare_node(node, specs_of):
    """
    Declare :data:`N_SENSORS` and :data:`PLUGINS`, import the plug-ins, then ``specs_of(S)``.

    Effect code is imported at start-up only (before the model is checked), never because a
    message names a module; a plug-in that fails is a ValueError (exit 2). Later changes go
    to the node's ``_on_set_parameters``. Returns (the specs by name, the effects registered).
    """
    first = declare(node, [N_SENSORS, PLUGINS])
    try:
        plugins = fx.load_plugins(value(node, 'plugins', []))
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f'plugins: {exc}') from None
    specs = {**declare(node, specs_of(int(value(node, 'n_sensors')))), **first}
    node.add_on_set_parameters_callback(node._on_set_parameters)
    return specs, plugins


def calibration_specs(n_sensors=4):
    """Parameters of ``calibration_node`` other than :data:`N_SENSORS`."""
    return [
        ParamSpec('model', ('base',),
                  'model to fit: list of formula terms (docs/formulas.md), e.g. '
                  "['base', 'temperature@2', 'offset(s(t, k=6))@2']; no unit",
                  model_check(n_sensors), item_type=str),
        ParamSpec('field_nt', 50000.0, 'reference magnitude of the (uniform) field at the '
                  'calibration site, nT', limits=(1.0, 1.0e6)),
        ParamSpec('calibration_file', default_calibration_file(),
                  'path of the calibration YAML written by calibration/calibrate (~ expanded; '
                  'the previous file is kept as <path>.bak; default under $ROS_HOME or '
                  '~/.ros); read-only: no parameter write may redirect a file write',
                  non_empty_path, read_only=True),
        ParamSpec('min_samples', 1000, 'fewest complete sample sets calibration/calibrate '
                  'accepts; count', limits=(12, 10 ** 9)),
        ParamSpec('max_samples', 20000, 'most sample sets held, spread evenly over the '
                  'whole run (when full, every other set is dropped and every other new one '
                  'kept); count, read-only', read_only=True, limits=(12, 10 ** 9)),
        ParamSpec('baseline_m', 0.5, 'distance between the two sensors of an arm of the '
                  'cross (paper 004), m', limits=(1.0e-3, 100.0)),
        ParamSpec('history', 20, 'number of previous calibrations kept in '
                  '<calibration_file>.history/ (0: none); count', limits=(0, 10000)),
        ParamSpec('report_dir', default_report_dir(), 'directory of the HTML report written '
                  'by calibration/diagnose (~ expanded; default under $ROS_HOME or ~/.ros); '
                  'read-only', non_empty_path, read_only=True),
        ParamSpec('stamp_tolerance_s', 0.005, 'largest header-stamp difference of two '
                  "sensors' samples that may vote for the same epoch when the streams are "
                  'aligned (about half a sample period), s', limits=(1.0e-6, 10.0)),
        ParamSpec('aux_topics', (), 'auxiliary std_msgs/Float64 topics (relative names) '
                  'recorded as columns aux_<name>; unit of each channel its own; read-only',
                  topic_names, read_only=True, item_type=str),
        ParamSpec('status_period_s', 1.0, 'period of calibration/status messages, s',
                  read_only=True, limits=(0.01, 3600.0)),
        ParamSpec('robust', False, 'use the robust (soft L1) loss against spikes; no unit'),
        ParamSpec('constrained', False, 'partial attitude coverage (a vehicle that cannot '
                  'turn over): priors on scale and angles in calibrate and diagnose, and a '
                  'partial coverage is not a missing item of the status; no unit'),
        ParamSpec('resync_sets', True, 'before a calibration or diagnosis, find sets whose '
                  'sensors the stamps paired from different epochs and re-pair them from the '
                  'data (magcal_ros.core.live.consistency); no unit'),
        ParamSpec('exclude_outliers', True, 'when the fit leaves a sensor above 1.5 x its '
                  'noise floor, exclude the sets beyond 5 sigma of a robust fit if they are '
                  'at most 5 % of all, and fit the rest (magcal_ros.pipeline.calibrate); no '
                  'unit'),
        ParamSpec('imu_topic', '', 'sensor_msgs/Imu topic whose orientation is the attitude '
                  'of the array (body-to-world, ENU, the IMU axes being the array axes), for '
                  "attitude-aided fits (attitude_mode) and the site_gradient effect; '' for "
                  'none; read-only', optional_topic, read_only=True),
        *geometry_specs(n_sensors),
        ParamSpec('field_source', 'constant', 'where the reference field magnitude comes '
                  'from: constant (field_nt), igrf (the IGRF model at site_latitude_deg, '
                  'site_longitude_deg, site_altitude_m and site_date) or shape (none: the '
                  "mean radius of sensor 1's data, shape only); no unit",
                  one_of(('constant', 'igrf', 'shape'))),
        ParamSpec('site_latitude_deg', math.nan, 'geodetic latitude of the calibration site '
                  'for field_source igrf, deg (.nan: not given)', latitude),
        ParamSpec('site_longitude_deg', math.nan, 'longitude of the calibration site for '
                  'field_source igrf, deg east (.nan: not given)', longitude),
        ParamSpec('site_altitude_m', 0.0, 'height of the calibration site above the WGS84 '
                  'ellipsoid for field_source igrf, m', limits=(-1.0e4, 1.0e6)),
        ParamSpec('site_date', '', 'date of the calibration for field_source igrf, YYYY-MM-DD '
                  "('' = the day the calibration is made, UTC)", iso_date),
        ParamSpec('attitude_mode', 'auto', 'how the attitude of imu_topic enters the fit: '
                  "tilt (roll and pitch observe the field's vertical component), full (the "
                  'heading too: the field vector), off (the magnitude alone), auto (tilt when '
                  'imu_topic is set; docs/design.md §2 "Attitude-aided fits"); no unit',
                  one_of(('auto', 'tilt', 'full', 'off'))),
        ParamSpec('planar', False, 'a robot that can only turn about one axis: calibrate '
                  'what the turn determines (in-plane offsets, scale ratio, angle: '
                  'heading-grade), hold the rest at the previous calibration or an ideal '
                  'sensor and name it undetermined (docs/planar.md); without it a turn about '
                  'one axis is refused; no unit'),
        ParamSpec('cmd_vel_topic', '/cmd_vel', 'geometry_msgs/Twist topic calibration/turn '
                  'drives the robot with; read-only', optional_topic, read_only=True),
        ParamSpec('turn_speed_rad_s', 0.3, 'angular speed of calibration/turn about the '
                  'robot z axis (positive: counter-clockwise seen from above), rad/s',
                  limits=(-3.0, 3.0)),
        ParamSpec('turn_count', 2.0, 'turns calibration/turn makes, as seen by sensor 1 (the '
                  'angle its in-plane reading sweeps); turns', limits=(0.25, 20.0)),
        ParamSpec('turn_timeout_s', 120.0, 'calibration/turn stops the robot after this long '
                  'even if the turns are not complete, s', limits=(1.0, 3600.0)),
    ]


def geometry_specs(n_sensors):
    """``sensor_positions_m`` and ``input_topics``, shared by both nodes."""
    return [
        ParamSpec('sensor_positions_m', (), 'array geometry: x y z of each sensor in the '
                  'array frame, flat (3 x n_sensors values), m; empty: paper 004 cross of '
                  'baseline_m for 4 sensors, the origin for 1; read-only',
                  positions_check(n_sensors), read_only=True, item_type=float),
        ParamSpec('input_topics', (), 'sensor_msgs/MagneticField topic of each sensor, '
                  "in sensor order (e.g. ['/imu/mag']); empty: the driver's sensor{j}/raw; "
                  'read-only', input_topics_check(n_sensors), read_only=True, item_type=str),
    ]


def _settings(cls, node):
    """``cls`` (a settings dataclass) from the node's current parameters."""
    got = {f.name: f.type(value(node, f.name, [])) for f in fields(cls)}
    got.update({k: os.path.expanduser(got[k]) for k in ('calibration_file', 'report_dir')
                if k in got})
    got['input_topics'] = default_input_topics(got['n_sensors'], got['input_topics'])
    return cls(**got)


def calibration_settings(node):
    """:class:`CalibrationSettings` from the node's current parameters."""
    return _settings(CalibrationSettings, node)


# -- corrector node -------------------------------------------------------------------------

def unit_quaternion(value):
    """Refuse anything but a unit quaternion (qw, qx, qy, qz)."""
    from magcal_ros.core.geometry.attitude import check_quaternions
    try:
        check_quaternions(np.asarray(value, float).reshape(1, -1))
    except ValueError as exc:
        return (f'must be a unit quaternion [qw, qx, qy, qz] (body-to-world, Hamilton, '
                f'scalar first), got {list(value)!r}: {exc}')
    return None


def corrector_specs(n_sensors=4):
    """Parameters of ``corrector_node`` other than :data:`N_SENSORS`."""
    return [
        ParamSpec('calibration_file', default_calibration_file(),
                  'calibration YAML loaded at start-up if present (~ expanded; default under '
                  '$ROS_HOME or ~/.ros); updates arrive on calibration/result; read-only',
                  non_empty_path, read_only=True),
        ParamSpec('stamp_tolerance_s', 0.005, 'largest header-stamp difference of two '
                  "sensors' samples that may vote for the same epoch when the streams are "
                  'aligned for the gradient tensor (about half a sample period), s',
                  limits=(1.0e-6, 10.0)),
        ParamSpec('aux_topics', (), 'auxiliary std_msgs/Float64 topics (relative names) '
                  'feeding the aux:aux_<name> effects of the calibration (latest value); '
                  'read-only', topic_names, read_only=True, item_type=str),
        ParamSpec('publish_gradient', True, 'publish the gradient tensor (T/m) on gradient; '
                  'no unit'),
        ParamSpec('diagnostics_period_s', 1.0, 'period of the /diagnostics status, s',
                  read_only=True, limits=(0.01, 3600.0)),
        ParamSpec('array_frame_id', DEFAULT_ARRAY_FRAME_ID, 'frame_id of the corrected fields '
                  'and of the gradient tensor: the array frame (sensor 1 orthogonalised); '
                  'the static transforms array -> fluxgate{j} are published from the '
                  "calibration when tf2_ros is importable; '' keeps each input's frame_id "
                  '(a single IMU magnetometer: its own frame, REP 145); read-only',
                  lambda v: None if v == '' else frame_id(v), read_only=True),
        ParamSpec('subtract_site_gradient', False, 'stationary test: subtract the site '
                  'gradient of the calibration (effect site_gradient), seen at site_attitude, '
                  'from the corrected fields and the tensor, leaving the anomaly; off: the '
                  'site gradient is part of the field and is ignored; no unit'),
        ParamSpec('site_attitude', (1.0, 0.0, 0.0, 0.0), 'attitude of the array during a '
                  'stationary test, body-to-world unit quaternion [qw, qx, qy, qz] in the '
                  "world frame of the calibration's site gradient; dimensionless",
                  unit_quaternion, item_type=float),
        *geometry_specs(n_sensors),
        ParamSpec('baseline_m', 0.5, 'distance between the two sensors of an arm of the '
                  'cross (paper 004; when sensor_positions_m is empty), m; read-only',
                  read_only=True, limits=(1.0e-3, 100.0)),
    ]


def _settings_class(name, node_name, specs):
    """Make a frozen dataclass with one field per parameter of ``specs`` (its default's type)."""
    return make_dataclass(name, [(spec.name, type(spec.default)) for spec in specs], frozen=True,
                          namespace={'__doc__': f'Settings of {node_name} (units in the names).'})


CalibrationSettings = _settings_class('CalibrationSettings', 'calibration_node',
                                      [N_SENSORS] + calibration_specs())
CorrectorSettings = _settings_class('CorrectorSettings', 'corrector_node',
                                    [N_SENSORS] + corrector_specs())


def corrector_settings(node):
    """:class:`CorrectorSettings` from the node's current parameters."""
    return _settings(CorrectorSettings, node)
