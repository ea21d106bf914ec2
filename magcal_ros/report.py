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
Diagnosis report: PNG figures and one self-contained HTML page (PNGs embedded as base64).

The figures answer "where does the model fail?": the residual over time, against every
driving signal and over the field direction, the gradient tensor, the candidates, the error
ladder and the model-free findings (:mod:`magcal_ros.core.discovery.findings`), the noise
floor on every residual plot.  Matplotlib's object API on the Agg canvas (no pyplot).
"""
import base64
import html
import io
from pathlib import Path
import re
import textwrap
import warnings

from magcal_ros.core.discovery import (AT_FLOOR_RATIO, compact_spec, MIN_DELTA_BIC,
                                       MIN_EXPLAINED, noise_floor_from_data)
from magcal_ros.core.discovery.findings import best_lag, view_of
from magcal_ros.core.discovery.measures import periodogram
from magcal_ros.core.discovery.run import report_progress
from magcal_ros.core.geometry.tensor import cross_positions, tensor_cross, tensor_noise_floor
import matplotlib
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import (AutoLocator, FuncFormatter, Locator, LogLocator, MaxNLocator,
                               NullLocator)
import numpy as np

#: at most this many points per scatter plot (evenly thinned; the extremes are added)
MAX_POINTS = 6000
#: a time series is reduced to its extremes in this many chunks (about the pixel width)
PIXEL_COLUMNS = 1000
COMPONENT_COLOURS = ('tab:red', 'tab:green', 'tab:blue')
DPI = 100
#: matplotlib settings of the figures: no glyph hinting (costly, and no better at 100 dpi)
RC = {'text.hinting': 'no_hinting'}
#: True: the figures' fixed margins (:func:`_arrange`); False: matplotlib's constrained
#: layout places the axes, the figure title and the bottom legends (bench/report_layout.py)
FIXED_LAYOUT = True


def _figure(width, height):
    """Return a figure on its own Agg canvas, without a layout engine (:func:`_arrange`)."""
    fig = Figure(figsize=(max(width, 7.0), height), dpi=DPI,
                 layout=None if FIXED_LAYOUT else 'constrained')
    FigureCanvasAgg(fig)
    return fig


def _suptitle(fig, text, fontsize=11):
    """Figure title wrapped to the figure width."""
    chars = int(fig.get_figwidth() * 110 / fontsize)
    at = {'y': 1.0 - 0.06 / fig.get_figheight(), 'va': 'top'} if FIXED_LAYOUT else {}
    fig.suptitle(textwrap.fill(text, chars), fontsize=fontsize, **at)


def _arrange(fig, rows=1, cols=1, left=0.8, right=0.25, bottom=0.55, top=0.3, wspace=1.0,
             hspace=0.75):
    """
    Place the grid of axes with fixed margins and gaps (inches); thin the ticks.

    ``left``/``bottom``: room for the tick and axis labels, ``top`` for the axes titles (plus
    the figure title), ``right`` for legends outside the axes.  With :data:`FIXED_LAYOUT`
    False, matplotlib's constrained layout places the axes instead.
    """
    w, h = fig.get_size_inches()
    title = fig.get_suptitle()
    if not FIXED_LAYOUT:
        return _thin_ticks(fig)
    if title:
        text = next(t for t in fig.texts if t.get_text() == title)
        size = text.get_fontsize() / 72.0                    # points -> inches
        top = top + 0.1 + 1.25 * size * (title.count('\n') + 1)
    cell_w = _cell_width(fig, cols, left, right, wspace)
    cell_h = max((h - top - bottom - (rows - 1) * hspace) / rows, 0.3)
    fig.subplots_adjust(left=left / w, right=1.0 - right / w, bottom=bottom / h,
                        top=1.0 - top / h, wspace=wspace / cell_w, hspace=hspace / cell_h)
    return _thin_ticks(fig)


def _thin_ticks(fig):
    """Give linear axes 3-5 major ticks and keep every axis' ticks inside its view."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            loc = axis.get_major_locator()
            if type(loc) is AutoLocator:
                axis.set_major_locator(_InView(MaxNLocator(
                    nbins=3, steps=[1, 2, 5, 10], min_n_ticks=3)))
            elif type(loc) is LogLocator:
                axis.set_major_locator(_InView(loc))
    return fig


def _cell_width(fig, cols=1, left=0.8, right=0.25, wspace=1.0):
    """Return the width of one axes that :func:`_arrange` gives these margins, inches."""
    return max((fig.get_figwidth() - left - right - (cols - 1) * wspace) / cols, 0.5)


def _columns(fig, cols=1, **margins):
    """Return the pixel columns of one axes of :func:`_arrange` (``margins`` as there)."""
    return int(np.ceil(DPI * _cell_width(fig, cols, **margins)))


class _InView(Locator):
    """Return the ticks of another locator that lie inside the view limits."""

    def __init__(self, inner):
        self.inner = inner

    # matplotlib's Locator API, to both locators or to the inner one
    def set_axis(self, axis):
        super().set_axis(axis)
        self.inner.set_axis(axis)

    def __call__(self):
        """Return the tick locations inside the view interval."""
        vmin, vmax = sorted(self.axis.get_view_interval())
        locs = np.asarray(self.inner())
        slack = 1e-9 * max(vmax - vmin, abs(vmin), abs(vmax))
        return locs[(locs >= vmin - slack) & (locs <= vmax + slack)]

    def tick_values(self, vmin, vmax):
        return self.inner.tick_values(vmin, vmax)

    def nonsingular(self, v0, v1):
        return self.inner.nonsingular(v0, v1)

    def view_limits(self, vmin, vmax):
        return self.inner.view_limits(vmin, vmax)


def _bottom_legend(fig, fontsize=7, axes=None, width=2.3, markerscale=2):
    """
    Put the legend of ``axes`` (default the first) along the bottom; return its margin, inches.

    (A 'best' legend inside the axes tests every data point: slow with thousands.)
    """
    handles = {}
    for ax in fig.axes[:1] if axes is None else axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    ncol = max(1, min(len(handles), int(fig.get_figwidth() / width)))
    fig.legend(list(handles.values()), list(handles), ncol=ncol,
               loc='lower center' if FIXED_LAYOUT else 'outside lower center',
               fontsize=fontsize, frameon=False, markerscale=markerscale)
    return 0.55 + 0.2 * int(np.ceil(len(handles) / ncol))


def _plain_log_ticks(*axes):
    """Give log axes plain decade labels ('0.01', '1e+04', no mathtext) and no minor ticks."""
    for axis in axes:
        axis.set_minor_locator(NullLocator())
        axis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:g}'))


def _message(ax, text, **kwargs):
    """Write ``text`` in the middle of an axes without data, its frame hidden."""
    ax.text(0.5, 0.5, text, ha='center', va='center', transform=ax.transAxes, **kwargs)
    ax.set_axis_off()


def _title(ax, text, **kwargs):
    """Set an axes title at a fixed height (an automatic one measures every tick label)."""
    ax.set_title(text, y=1.0, **kwargs)


def figure_png(fig):
    """Draw the figure on its Agg canvas and return it as PNG bytes (zlib level 1: fast)."""
    from PIL import Image
    fig.canvas.draw()
    buf = io.BytesIO()
    Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).save(
        buf, 'PNG', compress_level=1)
    return buf.getvalue()


def _thin(n):
    step = max(1, int(np.ceil(n / MAX_POINTS)))
    return np.arange(0, n, step)


def _envelope(y, columns=PIXEL_COLUMNS):
    """
    Return the indices of the smallest and largest sample of ``y`` in each of ``columns`` chunks.

    A line through them covers every pixel column's range (spikes stay visible).  ``y``: (N,)
    or (N, k) (the union over the k series), NaN skipped.  Returns sorted (M,) int indices.
    """
    y = np.asarray(y, float)
    n = len(y)
    k = n // columns
    if k <= 2:
        return np.arange(n)
    y2 = y.reshape(n, -1)
    head = np.where(np.isfinite(y2[:k * columns]), y2[:k * columns], np.nan)
    keep = np.zeros(n, bool)
    keep[k * columns:] = True                        # the last partial chunk: all of it
    for c in range(y2.shape[1]):
        blocks = head[:, c].reshape(columns, k)
        ok = np.isfinite(blocks).any(axis=1)
        start = np.arange(columns)[ok] * k
        keep[start + np.nanargmin(blocks[ok], axis=1)] = True
        keep[start + np.nanargmax(blocks[ok], axis=1)] = True
    return np.flatnonzero(keep)


def _band(ax, t, y, columns=PIXEL_COLUMNS, lw=0.5, **style):
    """
    Draw a series (``t``, ``y``: (N,)) as its range per chunk: one polygon, min to max per column.

    Looks like :func:`_envelope`'s line, drawn faster; ``lw`` (points) keeps a thin band
    visible; NaN leave a gap.  Returns the PolyCollection (legend handle).
    """
    n = len(y)
    k = int(np.ceil(n / columns))                # samples per chunk, the last one shorter
    if k <= 2:
        return ax.fill_between(t, y, y, lw=max(lw, 0.8), **style)
    chunks = int(np.ceil(n / k))
    blocks = np.full(chunks * k, np.nan)
    blocks[:n] = y
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)   # an all-NaN chunk: a gap
        lo = np.nanmin(blocks.reshape(chunks, k), axis=1)
        hi = np.nanmax(blocks.reshape(chunks, k), axis=1)
    edges = t[np.append(np.arange(0, n, k), n - 1)]
    x = np.repeat(edges, 2)[1:-1]                # each chunk flat from its edge to the next
    return ax.fill_between(x, np.repeat(lo, 2), np.repeat(hi, 2), lw=lw, **style)


def _scatter_idx(n, *series, columns=PIXEL_COLUMNS):
    """Return evenly thinned samples plus the extremes of every series per pixel column, sorted."""
    keep = np.zeros(n, bool)
    keep[_thin(n)] = True
    for y in series:
        keep[_envelope(y, columns)] = True
    return np.flatnonzero(keep)


def _binned(x, y, bins=20):
    """Centres and means of y in equal-count bins of x (NaN-free)."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2 * bins:
        return np.array([]), np.array([])
    parts = np.array_split(np.argsort(x), bins)
    return (np.array([x[p].mean() for p in parts]), np.array([y[p].mean() for p in parts]))


def _sensor_axes(fig, n, sharey=False):
    """Return ``n`` axes in rows of up to four (``sharey``: a row shares its y axis)."""
    cols = min(n, 4)
    rows = int(np.ceil(n / cols))
    if not sharey:
        return [fig.add_subplot(rows, cols, j + 1) for j in range(n)]
    axes = list(fig.subplots(rows, cols, sharey='row', squeeze=False).ravel())
    for ax in axes[n:]:
        fig.delaxes(ax)
    return axes[:n]


def _floor_lines(ax, level, label='noise floor'):
    """Draw +-``level`` across the axes as one dashed line (one artist, one legend entry)."""
    ax.plot([0.0, 1.0, np.nan, 0.0, 1.0], [level, level, np.nan, -level, -level], 'k--',
            lw=1.0, label=label, transform=ax.get_yaxis_transform())


# -- figures --------------------------------------------------------------------------------

def _magnitudes(data, result):
    """Return [((N,) |raw| - |B|, (N,) |model| - |B|) per sensor], nT."""
    f = result.field_magnitude_nt
    return [(np.linalg.norm(raw, axis=1) - f, np.linalg.norm(raw - res, axis=1) - f)
            for raw, res in zip(data.raw, result.residual_nt)]


def plot_magnitude(data, result):
    """Measured |raw| and modelled |forward(B)| per sensor over time, minus the reference |B|."""
    s = data.n_sensors
    fig = _figure(4.0 * min(s, 4), 3.2 * int(np.ceil(s / 4)))
    t = data.t - data.t[0]
    px = _columns(fig, min(s, 4))
    for j, (ax, (meas, model)) in enumerate(zip(_sensor_axes(fig, s),
                                                _magnitudes(data, result)), start=1):
        idx = _scatter_idx(len(t), meas, columns=px)
        ax.plot(t[idx], meas[idx], '.', ms=1.5, color='0.6', label='measured |raw| - |B|')
        idx = _envelope(model, px)
        ax.plot(t[idx], model[idx], '-', lw=0.8, color='tab:blue',
                label='model |A B + o + ...| - |B|')
        ax.axhline(0.0, color='k', lw=1.0, label='reference |B|')
        _title(ax, f'sensor {j}: |raw| - |B| mean {float(np.mean(meas)):+,.0f} nT', fontsize=9)
        ax.set(xlabel='time since start (s)', ylabel='|B| - reference (nT)')
    bottom = _bottom_legend(fig, fontsize=7)
    _suptitle(fig, 'Measured and modelled magnitude minus the reference |B| (mean '
              f'{float(np.mean(result.field_magnitude_nt)):,.0f} nT)', fontsize=10)
    return _arrange(fig, int(np.ceil(s / 4)), min(s, 4), bottom=bottom)


def plot_residual_time(data, result, floor):
    """Scalar and vector residual per sensor over time, with the noise floor (nT)."""
    s = data.n_sensors
    fig = _figure(12, 2.2 * s + 0.6)
    t = data.t - data.t[0]
    axes = np.atleast_1d(fig.subplots(s, 1, sharex=True))
    margins = {'right': 2.3}
    px = _columns(fig, **margins)
    for j, ax in enumerate(axes, start=1):
        scalar = result.scalar_residual_nt[j - 1]
        idx = _scatter_idx(len(t), scalar, columns=px)
        ax.plot(t[idx], scalar[idx], '.', ms=1.5, color='0.3', label='scalar |corrected| - |B|')
        if j > 1:
            for c in range(3):
                v = result.vector_residual_nt[j - 1, :, c]
                _band(ax, t, v, px, color=COMPONENT_COLOURS[c], alpha=0.6,
                      label=f'vector {"xyz"[c]}: sensor {j} - sensor 1')
        _floor_lines(ax, floor.per_sensor_nt[j - 1])
        ax.set_ylabel(f'sensor {j}\nresidual (nT)')
        if j == s:
            ax.set_xlabel('time since start (s)')
        if j == min(s, 2):               # one legend: the other sensors' differ only in j
            ax.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0))
    _suptitle(fig, f'Residual over time (model {",".join(compact_spec(result.model))})',
              fontsize=11)
    return _arrange(fig, s, 1, top=0.05, hspace=0.12, **margins)


def _unit_of(channel):
    """Return the unit of an auxiliary channel for an axis label ('channel unit' if unknown)."""
    from magcal_ros.units import channel_unit
    return channel_unit(channel) or 'channel unit'


def adopted_fit(data, diagnosis, ladder=None):
    """Return the fit with the verdict's term added (the ladder's rung or a refit), or None."""
    tok = diagnosis.verdict_token if diagnosis is not None else None
    if not tok:
        return None
    if ladder is not None and len(ladder.steps) > 1 and ladder.steps[1].added == tok:
        return ladder.steps[1].result
    from magcal_ros.core.effects.attitude_ref import attitude_reference
    from magcal_ros.core.model import fit
    base = diagnosis.result
    try:
        model = base.model.with_effect(tok)           # an aided fit keeps its priors
        return fit(data, model, field_nt=base.field_magnitude_nt, on_degenerate='flag',
                   check_identifiability=False, covariance=False,
                   constrained=attitude_reference(model) is not None)
    except (ValueError, np.linalg.LinAlgError):
        return None


def verdict_driver(data, token, j, term=None):
    """
    Return what the verdict's term follows on sensor j: (name, axis label, (N,) values).

    A channel in the token, a period's phase, |d raw / dt| for the field rate, the raw
    component a direction term varies with most (``term``: its (N,) scalar fit), else time.
    """
    t = data.t - data.t[0]
    if not token:
        return 'time', 'time since start (s)', t
    if 'temperature' in token and data.temp is not None:
        return 'temperature', f'sensor {j} temperature (degC)', data.temp[j - 1]
    for name in sorted(data.aux or {}, key=len, reverse=True):
        if name in token:
            return name, f'{name} ({_unit_of(name)})', data.aux[name]
    m = re.search(r'periodic\(([0-9.eE+-]+)', token)
    if m:
        period = 1.0 / float(m.group(1))
        return 'phase', f'phase of the {period:.4g} s period (cycles)', (t / period) % 1.0
    if 'field_rate' in token:
        rate = data.context(j).raw_rate
        if rate is not None:
            return 'field rate', '|d raw / dt| (nT/s)', np.linalg.norm(rate, axis=1)
    if any(e in token for e in ('nonlinearity', 'soft_iron')):
        raw = data.raw[j - 1]
        k = 0
        if term is not None and np.std(term) > 0:
            k = int(np.argmax([abs(np.corrcoef(raw[:, c], term)[0, 1]) for c in range(3)]))
        return f'raw {"xyz"[k]}', f'raw {"xyz"[k]} reading (nT)', raw[:, k]
    return 'time', 'time since start (s)', t


def plot_structure(data, result, floor, diagnosis=None, adopted=None, findings=None):
    """
    Draw the residual per sensor, scalar and vector, over time and against the driver.

    Columns: the scalar and the vector residual over time, the residual in the sensor's axes
    against :func:`verdict_driver` (no verdict: the first finding's channel); over each, the
    adopted term's fit (``result`` minus ``adopted``).  (CAPTIONS['structure'] says more.)
    """
    s = data.n_sensors
    token = diagnosis.verdict_token if diagnosis is not None else None
    chan = (None if token or findings is None else
            next((f.channel for f in findings.items if f.channel), None))
    cols = 3 if (token or chan) else 2
    fig = _figure(4.6 * cols, 2.3 * s + 0.9)
    t = data.t - data.t[0]
    margins = {'left': 0.9, 'wspace': 0.9}
    px = _columns(fig, cols, **margins)
    axes = fig.subplots(s, cols, squeeze=False)
    ratio = {j: v / floor.per_sensor_nt[j - 1] for j, v in result.scalar_rms_nt.items()}
    for j in range(1, s + 1):
        scalar = result.scalar_residual_nt[j - 1]
        term = None if adopted is None else scalar - adopted.scalar_residual_nt[j - 1]
        ax = axes[j - 1, 0]
        idx = _scatter_idx(len(t), scalar, columns=px)
        ax.plot(t[idx], scalar[idx], '.', ms=1.2, color='0.55', label='scalar residual')
        if term is not None:
            e = _envelope(term, px)
            ax.plot(t[e], term[e], '-', lw=1.0, color='tab:red',
                    label=f'fit of {token} (what it takes out)')
        _floor_lines(ax, floor.per_sensor_nt[j - 1])
        after = ('' if adopted is None else f' -> {adopted.scalar_rms_nt[j]:.2f} nT with {token}')
        _title(ax, f'sensor {j}: scalar RMS {result.scalar_rms_nt[j]:.2f} nT '
               f'({ratio[j]:.2f} x floor){after}', fontsize=8, loc='left')
        ax.set(ylabel='scalar (nT)', xlabel='time since start (s)')
        ax = axes[j - 1, 1]
        if j == 1:
            _message(ax, 'sensor 1 defines the array frame:\nthe vector residuals of the '
                     'others are taken against it', fontsize=8)
        else:
            vec = result.vector_residual_nt[j - 1]
            for c in range(3):
                _band(ax, t, vec[:, c], px, color=COMPONENT_COLOURS[c], alpha=0.45,
                      label=f'vector {"xyz"[c]} (sensor j - sensor 1)')
            if adopted is not None:
                vt = vec - adopted.vector_residual_nt[j - 1]
                e = _envelope(vt, px)
                ax.plot(t[e], vt[e], '-', lw=0.9, color='k', label='fit of the term, x y z')
            _floor_lines(ax, floor.vector_floor_nt(j))
            vr = result.vector_rms_nt.get(j, float('nan'))
            _title(ax, f'sensor {j} - sensor 1: vector RMS {vr:.2f} nT', fontsize=8, loc='left')
            ax.set(ylabel='vector (nT)', xlabel='time since start (s)')
        if cols == 3:
            ax = axes[j - 1, 2]
            if token:
                name, xlabel, x = verdict_driver(data, token, j, term)
            else:
                name, xlabel = chan, f'{chan} ({_unit_of(chan)})'
                x = (data.temp[j - 1] if chan == 'temperature' and data.temp is not None
                     else (data.aux or {}).get(chan))
            if x is None or not np.isfinite(x).any():
                _message(ax, f'no {name} on sensor {j}')
                continue
            # in the sensor's axes an additive term shows whole, not projected on the field
            idx = _thin(len(x))
            raw_res = result.residual_nt[j - 1]
            for c in range(3):
                ax.plot(x[idx], raw_res[idx, c], '.', ms=1.0, alpha=0.5,
                        color=COMPONENT_COLOURS[c], label=f'residual {"xyz"[c]}, sensor axes')
            if adopted is not None and j in _token_sensors(token, s):
                rt = raw_res - adopted.residual_nt[j - 1]
                ax.plot(x[idx], rt[idx], '.', ms=0.6, color='k')
            _floor_lines(ax, floor.per_sensor_nt[j - 1])
            _title(ax, f'sensor {j}: residual x y z vs {name}', fontsize=8, loc='left')
            ax.set(ylabel='sensor axes (nT)', xlabel=xlabel)
    bottom = _bottom_legend(fig, 7, axes.ravel(), width=3.2, markerscale=3)
    head = (f'verdict {token}: its fit (red, black) drawn over the residual it explains'
            if token and adopted is not None else
            f'verdict {token} (its fit could not be drawn)' if token else
            'no verdict: the residual as it is'
            + (f', against {chan} (a finding names it)' if chan else ''))
    _suptitle(fig, f'Residual per sensor over time and against the driver; {head} '
              f'(model {",".join(compact_spec(result.model))})', fontsize=10)
    return _arrange(fig, s, cols, bottom=bottom, hspace=0.85, **margins)


def _driver_panels(data, result, floor, drivers, title, xlabel):
    """Residual per sensor against each of ``drivers`` [(name, values(j) -> (N,), sensors)]."""
    cols = max(len(sensors) for _, _, sensors in drivers)
    fig = _figure(4.0 * cols, 3.0 * len(drivers) + 0.5)
    idx = _thin(data.n_samples)
    for r, (name, values, sensors) in enumerate(drivers):
        for i, j in enumerate(sensors):
            x = values(j)
            ax = fig.add_subplot(len(drivers), cols, r * cols + i + 1)
            if x is None or not np.isfinite(x).any():
                _message(ax, 'no data')
                continue
            ax.plot(x[idx], result.scalar_residual_nt[j - 1, idx], '.', ms=1.5, color='0.6',
                    label='scalar residual')
            for c in range(3):
                bx, by = _binned(x, result.residual_nt[j - 1, :, c])
                ax.plot(bx, by, '-o', ms=2.5, lw=1.2, color=COMPONENT_COLOURS[c],
                        label=f'raw residual {"xyz"[c]} (bin mean)')
            _floor_lines(ax, floor.per_sensor_nt[j - 1])
            _title(ax, f'sensor {j} vs {name}', fontsize=9)
            ax.set(xlabel=xlabel(name), ylabel='residual (nT)')
    bottom = _bottom_legend(fig, fontsize=7)
    _suptitle(fig, title, fontsize=11)
    return _arrange(fig, len(drivers), cols, bottom=bottom)


def _all_sensors(data, sensors):
    return list(range(1, data.n_sensors + 1)) if sensors is None else sorted(sensors)


def plot_residual_vs_temperature(data, result, floor, sensors=None):
    """Residual of each sensor (of ``sensors``, default all) against its temperature, or None."""
    if data.temp is None or not np.isfinite(data.temp).any():
        return None
    return _driver_panels(
        data, result, floor,
        [('temperature', lambda j: data.temp[j - 1], _all_sensors(data, sensors))],
        'Residual vs sensor temperature (a trend = a temperature coefficient)',
        lambda n: 'sensor temperature (degC)')


def plot_residual_vs_aux(data, result, floor, channels=None):
    """
    Residual of each sensor against each auxiliary channel, or None without any.

    ``channels``: names of ``data.aux`` or {name: sensors (1-based) or None} (default all).
    """
    if not isinstance(channels, dict):
        channels = dict.fromkeys((data.aux or {}) if channels is None else channels)
    drivers = [(k, (lambda j, k=k: data.aux[k]), _all_sensors(data, channels[k]))
               for k in sorted(channels) if k in (data.aux or {})]
    if not drivers:
        return None
    return _driver_panels(data, result, floor, drivers,
                          'Residual vs auxiliary channels (a trend = a coupling of that channel)',
                          lambda n: f'{n} ({_unit_of(n)})')


def plot_residual_vs_rate(data, result, floor):
    """Residual magnitude against |dB/dt| of each sensor, or None without a time axis."""
    s = data.n_sensors
    rates = [data.context(j).raw_rate for j in range(1, s + 1)]
    if rates[0] is None:
        return None
    fig = _figure(4.0 * min(s, 4), 3.2 * int(np.ceil(s / 4)) + 0.4)
    idx = _thin(data.n_samples)
    for j, ax in enumerate(_sensor_axes(fig, s), start=1):
        x = np.linalg.norm(rates[j - 1], axis=1)
        ax.plot(x[idx], np.abs(result.scalar_residual_nt[j - 1, idx]), '.', ms=1.5,
                color='0.6', label='|scalar residual|')
        ax.plot(*_binned(x, np.abs(result.scalar_residual_nt[j - 1])), '-o', ms=2.5, color='0.2',
                label='|scalar| bin mean')
        if j > 1:
            v = np.linalg.norm(result.vector_residual_nt[j - 1], axis=1)
            ax.plot(x[idx], v[idx], '.', ms=1.5, color='tab:orange', alpha=0.5,
                    label='|vector residual| vs sensor 1')
            ax.plot(*_binned(x, v), '-o', ms=2.5, color='tab:red', label='|vector| bin mean')
            ax.axhline(np.sqrt(3) * floor.vector_floor_nt(j), color='tab:red', ls=':', lw=1,
                       label='|vector| noise floor (RMS)')
        ax.axhline(floor.per_sensor_nt[j - 1], color='k', ls='--', lw=1, label='noise floor')
        _title(ax, f'sensor {j}', fontsize=9)
        ax.set(xlabel='|d raw / dt| (nT/s)', ylabel='residual magnitude (nT)')
    fig.axes[-1].legend(fontsize=6, loc='upper left')
    _suptitle(fig, 'Residual vs field rate (a rising |vector| = lag / eddy currents / '
              'sampling skew)', fontsize=11)
    return _arrange(fig, int(np.ceil(s / 4)), min(s, 4))


def direction_projection(b, centre=None):
    """
    Lambert azimuthal equal-area projection of field directions ``b`` (N, 3), without a seam.

    About ``centre`` (3,), default the mean direction (+z when it is ~0): the sphere is a disc
    of radius 2, the point density the coverage.  Returns x (N,), y (N,) in [-2, 2], centre.
    """
    u = np.asarray(b, float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    c = np.mean(u, axis=0) if centre is None else np.asarray(centre, float)
    if np.linalg.norm(c) < 0.2:
        c = np.array([0.0, 0.0, 1.0])
    c = c / np.linalg.norm(c)
    # tangent basis at the centre: e1 along the sensor x (or y) axis' perpendicular part
    ref = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ c) * c
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    cos_d = np.clip(u @ c, -1.0, 1.0)
    k = np.sqrt(2.0 / np.maximum(1.0 + cos_d, 1e-12))
    return k * (u @ e1), k * (u @ e2), c


def plot_direction_map(data, result, floor):
    """Scalar residual over field direction in the sensor frame (equal-area, no seam)."""
    s = data.n_sensors
    fig = _figure(4.4 * min(s, 4), 3.6 * int(np.ceil(s / 4)) + 0.4)
    idx = _thin(data.n_samples)
    for j, ax in enumerate(_sensor_axes(fig, s), start=1):
        b = result.corrected_nt[j - 1, idx]       # raw directions are skewed by the offset
        x, y, c = direction_projection(b)
        r = result.scalar_residual_nt[j - 1, idx]
        lim = max(3.0 * floor.per_sensor_nt[j - 1], float(np.percentile(np.abs(r), 98)))
        # no marker outline: Agg stroking each edge was a third of this figure's drawing
        sc = ax.scatter(x, y, c=r, s=9, linewidths=0, cmap='coolwarm', vmin=-lim, vmax=lim)
        fig.colorbar(sc, ax=ax, fraction=0.046, pad=0.03).set_label('scalar residual (nT)')
        # rings 45, 90 and 135 deg from the centre direction, and the edge of the sphere
        rings = [2 * np.sin(np.radians(deg) / 2) for deg in (45, 90, 135)]
        for rr, ls in zip(rings + [2.0], ':::-'):
            ax.add_patch(Circle((0.0, 0.0), rr, fill=False, color='0.5', lw=0.7, ls=ls))
        ax.set(xlim=(-2.05, 2.05), ylim=(-2.05, 2.05))
        ax.set_aspect('equal')
        ax.set(xlabel='equal-area x (rings: 45, 90, 135 deg from centre)',
               ylabel='equal-area y (centre = mean direction)')
        _title(ax, f'sensor {j}: centre ({c[0]:+.2f}, {c[1]:+.2f}, {c[2]:+.2f}), floor '
               f'{floor.per_sensor_nt[j - 1]:.1f} nT', fontsize=8)
    _suptitle(fig, 'Residual over field direction (sensor frame, equal-area)', fontsize=11)
    return _arrange(fig, int(np.ceil(s / 4)), min(s, 4), right=0.6, wspace=1.3)


def plot_tensor(data, result, baseline_m=0.5, floor=None):
    """
    Gradient tensor components (paper 004 eq. 1) before/after correction, nT/m.

    The floor line: ``floor`` (a NoiseFloor; default estimated here) propagated to the tensor.
    """
    if data.n_sensors != 4:
        return None
    before = tensor_cross(data.raw, baseline_m)
    after = tensor_cross(result.corrected_nt, baseline_m)
    if floor is None:
        floor = noise_floor_from_data(data, result)
    floor = tensor_noise_floor(floor.per_sensor_nt, cross_positions(baseline_m))
    t = data.t - data.t[0]
    fig = _figure(12, 6.5)
    comps = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    axes = fig.subplots(2, 1, sharex=True)
    margins = {'right': 2.6}
    px = _columns(fig, **margins)
    for k, (g, label) in enumerate(((before, 'before (raw readings)'),
                                    (after, 'after correction'))):
        ax = axes[k]
        for n, (a, b) in enumerate(comps):
            name = f'G{"xyz"[a]}{"xyz"[b]}'
            if k == 1:                  # after: noise about zero, drawn as its range
                _band(ax, t, g[:, a, b], px, color=f'C{n}', alpha=0.7, label=name)
            else:                       # before: smooth curves, one line each
                idx = _envelope(g[:, a, b], px)
                ax.plot(t[idx], g[idx, a, b], '-', lw=0.7, color=f'C{n}', label=name)
        if k == 1:
            lev = float(np.max(floor))
            ax.axhline(lev, color='k', ls='--', lw=1, label='noise floor (largest component)')
            ax.axhline(-lev, color='k', ls='--', lw=1)
        rms = np.sqrt(np.mean((g - g.mean(axis=0)) ** 2, axis=0))
        _title(ax, f'gradient tensor {label}: RMS up to {rms.max():.1f} nT/m', fontsize=10)
        ax.set_ylabel('tensor component (nT/m)')
    axes[1].legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0))
    fig.axes[-1].set_xlabel('time since start (s)')
    _suptitle(fig, f'Gradient tensor of the cross (baseline {baseline_m} m), uniform field: '
              'ideally zero', fontsize=11)
    return _arrange(fig, 2, 1, hspace=0.35, **margins)


def candidate_chart_data(diagnosis, top=15):
    """
    Return the candidates chart's rows (best first), one dict per candidate.

    Keys: token, significant, likelihood_tests (p-value and BIC passed), explained_fraction
    (0..1 or None), verdict, held_out_before/after/drop_nt (nT or None), evidence (-delta BIC).
    """
    rows = []
    for c in list(diagnosis.candidates)[:top]:
        d = c.to_dict()
        before, after = d.get('cv_rms_before_nt'), d.get('cv_rms_after_nt')
        drop = None if before is None or after is None else float(before - after)
        dbic = d.get('delta_bic')
        lr_ok = (d.get('p_value') is not None and d['p_value'] < diagnosis.p_threshold
                 and dbic is not None and dbic < MIN_DELTA_BIC)
        rows.append({'token': d['token'], 'significant': bool(d.get('significant')),
                     'likelihood_tests': bool(lr_ok),
                     'explained_fraction': d.get('explained_fraction'),
                     'verdict': d['token'] == diagnosis.verdict_token,
                     'held_out_before_nt': before, 'held_out_after_nt': after,
                     'held_out_drop_nt': drop,
                     'evidence': None if dbic is None or not np.isfinite(dbic) else -dbic})
    return rows


def plot_candidates(diagnosis, top=15):
    """
    Plot what decided the verdict: each candidate's share of the excess removed, -delta BIC.

    Green: passes every test; orange: the likelihood tests only; grey: not significant; a
    cross: share not tested; the verdict's bar outlined.
    """
    rows = candidate_chart_data(diagnosis, top)
    if not rows:
        return None
    fig = _figure(12, 0.35 * len(rows) + 1.8)
    # the right panel repeats the rows without tick marks (sharey would make each tick twice)
    ax, ax2 = fig.subplots(1, 2, width_ratios=[3, 2])
    y = np.arange(len(rows))[::-1]
    colours = ['tab:green' if r['significant'] else
               ('tab:orange' if r['likelihood_tests'] else '0.7') for r in rows]
    share = np.array([r['explained_fraction'] or 0.0 for r in rows])
    bars = ax.barh(y, share, color=colours)
    for bar, r in zip(bars, rows):
        if r['verdict']:
            bar.set(edgecolor='k', linewidth=2)
    for yi, r in zip(y, rows):
        if r['explained_fraction'] is not None:
            txt = f'{r["explained_fraction"]:.0%}'
            if r['held_out_drop_nt'] is not None:
                txt += (f' (held-out {r["held_out_before_nt"]:.2f} -> '
                        f'{r["held_out_after_nt"]:.2f} nT)')
            ax.text(0, yi, f'  {txt}', va='center', fontsize=7)
    untested = [yi for yi, r in zip(y, rows) if r['explained_fraction'] is None]
    if untested:
        ax.plot(np.full(len(untested), 0.012), untested, 'x', ms=5, color='0.4',
                clip_on=False, label='share not tested')
    ax.axvline(MIN_EXPLAINED, color='k', ls='--', lw=1,
               label=f'a verdict removes >= {MIN_EXPLAINED:.0%}')
    ax.set_xlim(0, 1)
    ax.set_yticks(y, [r['token'] for r in rows], fontsize=8)
    ax.set_ylabel('candidate effect (model token)')
    ax.set_xlabel(f'share of the excess over the floor removed ({diagnosis.decided_by}): '
                  'decides the verdict')
    ax.legend(fontsize=7, loc='lower right')
    ev = np.array([max(r['evidence'], 0.1) if r['evidence'] is not None else 0.1 for r in rows])
    ax2.barh(y, ev, color=colours)
    ax2.set_ylim(ax.get_ylim())
    ax2.set_yticks([])
    ax2.set_xscale('log')
    _plain_log_ticks(ax2.xaxis)
    ax2.axvline(-MIN_DELTA_BIC, color='k', ls='--', lw=1)
    ax2.set(xlabel='-delta BIC (log scale): must exceed 10 (dashed)', ylabel='(same candidates)')
    _suptitle(fig, 'Candidate effects, best first; verdict: '
              f'{diagnosis.verdict_token or "none"}', fontsize=10)
    # room for the longest effect token (8 pt: ~0.065 in per character) and the axis label
    longest = max(len(r['token']) for r in rows)
    return _arrange(fig, 1, 2, left=0.45 + 0.065 * longest, top=0.05, bottom=0.6, wspace=0.5)


def plot_ladder_rungs(data, ladder):
    """Scalar residual over time of every rung's fit (one row per rung), with its model."""
    steps = [st for st in ladder.steps if st.result is not None]
    if not steps:
        return None
    fl = ladder.noise_floor
    fig = _figure(11, 1.9 * len(steps) + 0.8)
    axes = np.atleast_1d(fig.subplots(len(steps), 1, sharex=True))
    t = data.t - data.t[0]
    px = _columns(fig)
    for ax, (i, st) in zip(axes, enumerate(steps)):
        res = st.result.scalar_residual_nt
        for j in range(res.shape[0]):
            idx = _scatter_idx(len(t), res[j], columns=px)
            ax.plot(t[idx], res[j, idx], ',' if len(idx) > 3000 else '.', ms=1.5,
                    label=f'sensor {j + 1}', alpha=0.6)
        _floor_lines(ax, 3 * fl.value_nt, label='3 x floor')
        worst = max(v / fl.per_sensor_nt[j - 1] for j, v in st.scalar_rms_nt.items())
        what = 'start: ' + ','.join(st.model) if st.added is None else f'+ {st.added}'
        _title(ax, f'rung {i}: {what} (worst scalar RMS {worst:.2f} x floor)', fontsize=9,
               loc='left')
        ax.set_ylabel('scalar residual (nT)', fontsize=8)
    axes[0].legend(fontsize=7, loc='upper right', ncol=4, markerscale=6)
    axes[-1].set_xlabel('time since start (s)')
    _suptitle(fig, 'Error ladder: scalar residual of each rung. Stopped: '
              + (ladder.reason[:110] + ('...' if len(ladder.reason) > 110 else '')), fontsize=10)
    return _arrange(fig, len(steps), 1, hspace=0.4)


def plot_ladder(ladder):
    """Waterfall of the held-out RMS per step of the error ladder, with the noise floor."""
    steps = ladder.steps
    fig = _figure(max(6.0, 1.6 * len(steps) + 2), 4.2)
    ax = fig.add_subplot(1, 1, 1)
    cv = np.array([st.residual_rms_nt if st.cv_rms_nt is None else st.cv_rms_nt for st in steps])
    x = np.arange(len(steps))
    ax.bar(x[:1], cv[:1], color='tab:gray', width=0.6, label='start')
    if len(steps) > 1:
        ax.bar(x[1:], np.abs(np.diff(cv)), bottom=np.minimum(cv[:-1], cv[1:]), width=0.6,
               color=['tab:green' if c < p else 'tab:red' for c, p in zip(cv[1:], cv[:-1])],
               label='change from adding the effect')
    ax.plot(x, cv, 'ko-', ms=4, lw=1, label='held-out RMS')
    ax.plot(x, [st.residual_rms_nt for st in steps], 'bx', label='in-sample RMS')
    fl = ladder.noise_floor.value_nt
    ax.axhline(fl, color='k', ls='--', lw=1, label=f'noise floor {fl:.2f} nT')
    for xi, v in zip(x, cv):
        ax.text(xi + 0.08, v, f'{v:.2f} nT', ha='left', va='bottom', fontsize=8)
    ax.set_xticks(x, ['start:\n' + ','.join(steps[0].model)]
                  + [f'+ {st.added}' for st in steps[1:]], fontsize=8)
    ax.set(xlabel='model (effect added at each step)', ylabel='combined residual RMS (nT)')
    ax.set_ylim(0, 1.15 * max(cv.max(), fl))
    _title(ax, 'Error ladder: held-out residual as effects are added', fontsize=11)
    # outside the axes: inside, any corner can cover a step (the last one, at upper right)
    ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    return _arrange(fig, right=2.2, bottom=0.85, top=0.4)


# -- model-free findings (magcal_ros.core.discovery.findings) -------------------------------

def plot_residual_spectrum(findings):
    """Power spectrum of each sensor's residual series (``findings``') over its white noise."""
    sensors = sorted(findings.series)
    if not sensors or len(findings.t) < 30:
        return None
    fig = _figure(3.6 * min(len(sensors), 4), 3.2 * int(np.ceil(len(sensors) / 4)))
    # one power axis per row: power over the white-noise level compares across sensors
    for i, (ax, j) in enumerate(zip(_sensor_axes(fig, len(sensors), sharey=True), sensors)):
        freqs, power, _ = periodogram(findings.t, findings.series[j])
        z = power.sum(axis=1) / np.sum(findings.noise_nt[j] ** 2)
        # about 400 log-spaced bins, each drawn at its maximum so that lines stay visible
        edges = np.unique(np.searchsorted(freqs, np.geomspace(freqs[0], freqs[-1], 400)))
        ax.loglog(freqs[edges], np.maximum.reduceat(z, edges), lw=0.8, color='tab:blue')
        _plain_log_ticks(ax.xaxis, ax.yaxis)
        ax.axhline(1.0, color='k', ls='--', lw=1.0, label='white noise')
        for f in findings.items:
            if view_of(f) == 'residual_spectrum' and f.sensor == j:
                ax.axvline(f.value, color='tab:red', lw=1.0, alpha=0.7)
                ax.annotate(f.token or f.kind, (f.value, 1.0), fontsize=8, color='tab:red',
                            xycoords=('data', 'axes fraction'), ha='center', va='top')
        ax.set_xlabel('frequency [Hz]')
        if i % min(len(sensors), 4) == 0:           # the first of its row
            ax.set_ylabel('power / white noise')
        _title(ax, f'sensor {j}', fontsize=10)
    _suptitle(fig, f'Residual spectrum per sensor ({findings.kind_of_series} residual)')
    return _arrange(fig, int(np.ceil(len(sensors) / 4)), min(len(sensors), 4), wspace=0.35)


def plot_change_points(findings):
    """Each sensor's residual series over time (running mean) with the steps found."""
    sensors = sorted(findings.series)
    n = len(findings.t)
    if not sensors or n < 30:
        return None
    from scipy.ndimage import uniform_filter1d
    t = findings.t
    w = max(3, n // 100)
    fig = _figure(3.6 * min(len(sensors), 4), 3.2 * int(np.ceil(len(sensors) / 4)))
    idx = np.arange(0, n, max(1, n // 1500))
    for ax, j in zip(_sensor_axes(fig, len(sensors)), sensors):
        x = findings.series[j] - findings.series[j].mean(axis=0)
        sm = uniform_filter1d(x, w, axis=0, mode='nearest')
        steps = sorted(f.value for f in findings.items
                       if view_of(f) == 'change_points' and f.sensor == j)
        edges = [0] + [int(np.searchsorted(t, v)) for v in steps] + [n]
        for c in range(x.shape[1]):
            colour = COMPONENT_COLOURS[c] if x.shape[1] == 3 else 'tab:blue'
            ax.plot(t[idx], sm[idx, c], lw=0.6, color=colour, alpha=0.6)
            for a, b in zip(edges[:-1], edges[1:]):
                if b > a:
                    ax.plot([t[a], t[b - 1]], [x[a:b, c].mean()] * 2, lw=1.5, color=colour)
        band = float(np.sqrt(np.mean(findings.noise_nt[j] ** 2)) / np.sqrt(w))
        _floor_lines(ax, band, label='noise of the running mean')
        for v in steps:
            ax.axvline(v, color='k', lw=1.0, alpha=0.6)
            ax.annotate(f'step({v:.6g})@{j}', (v, ax.get_ylim()[1]), fontsize=8,
                        ha='left', va='top')
        ax.set(xlabel='t [s]', ylabel='residual [nT]')
        _title(ax, f'sensor {j}: {len(steps)} change point(s)', fontsize=10)
    _suptitle(fig, f'Change points (running mean over {w} samples)')
    return _arrange(fig, int(np.ceil(len(sensors) / 4)), min(len(sensors), 4), wspace=0.75)


def plot_residual_vs_lagged_channels(data, findings):
    """
    Residual against each driving channel found, as is and through the lag found.

    The residual along the direction it moves with the channel, binned; without a lag,
    channel or channel_nonlinear finding, each sensor's temperature at its best lag.
    """
    from magcal_ros.core.effects import first_order_lag
    t = findings.t
    if len(t) < 30:
        return None
    panels = [(f.sensor, f.channel, f.value if f.kind == 'lag' else 0.0, f.token or f.kind)
              for f in findings.items if view_of(f) == 'residual_lagged' and f.channel]
    if not panels and data.temp is not None:
        panels = [(j, 'temperature', None, 'no finding') for j in sorted(findings.series)
                  if np.all(np.isfinite(data.temp[j - 1]))]
    panels = panels[:4]
    if not panels:
        return None
    fig = _figure(3.6 * len(panels), 3.4)
    for ax, (j, ch, tau, label) in zip(_sensor_axes(fig, len(panels)), panels):
        if ch == 'temperature':
            drive = (np.mean(data.temp, axis=0) if j is None else data.temp[j - 1])
        else:
            drive = np.asarray(data.aux[ch], float)
        y = findings.common if j is None else findings.series[j]
        if y is None:
            continue
        y = y - y.mean(axis=0)
        if y.shape[1] == 1 and findings.direction is not None:
            # a scalar residual shows a vector effect along the field: 3 (u.e) u ~ e
            y = 3.0 * y * findings.direction
        if tau is None:
            tau = best_lag(t, y, drive)
        lagged = first_order_lag(t, drive, tau) if tau else drive
        # the direction the residual moves with the channel (and its square: an even coupling)
        z = (lagged - lagged.mean()) / (np.std(lagged) or 1.0)
        a = np.column_stack([np.ones(len(t)), z, z ** 2])
        coef = np.linalg.lstsq(a, y, rcond=None)[0][1:]
        d = np.linalg.svd(coef, full_matrices=False)[2][0]
        proj = y @ d
        curves = [(drive, ch, 'tab:grey')]
        if tau:
            curves.append((lagged, f'{ch} lagged {tau:.3g} s', 'tab:red'))
        for xv, name, colour in curves:
            ax.plot(*_binned(xv, proj, bins=30), 'o-', ms=3, lw=1.0, color=colour, label=name)
        ax.set(xlabel=ch, ylabel='residual along its direction [nT]')
        _title(ax, f'{"all sensors" if j is None else f"sensor {j}"}: {label}', fontsize=10)
        if len(curves) > 1:                 # one curve: the x label names it
            ax.legend(fontsize=8)
    _suptitle(fig, 'Residual against the driving channels')
    return _arrange(fig, 1, len(panels))


# -- the page -------------------------------------------------------------------------------

def finding_rows(findings):
    """Rows of the findings table (strings)."""
    return [[f.kind, 'all' if f.sensor is None else f.sensor, f.channel or '',
             '' if f.value is None else f'{f.value:.4g} {f.unit}'.strip(),
             f'{f.explained_fraction:.2f}', f.token or '', f.text] for f in findings.items]


FINDING_HEADER = ('kind', 'sensor', 'channel', 'value', 'share of excess', 'add', 'what')


def _table(rows, header):
    head = ''.join(f'<th>{html.escape(h)}</th>' for h in header)
    body = ''.join('<tr>' + ''.join(f'<td>{html.escape(str(c))}</td>' for c in r) + '</tr>'
                   for r in rows)
    return f'<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _nt(value):
    """Return a residual RMS, nT, as text; '-' when not evaluated (a score-test candidate)."""
    return '-' if value is None else f'{value:.2f}'


def candidate_rows(diagnosis):
    """Rows of the candidate table (strings)."""
    return [[c.token, c.n_params, f'{c.delta_bic:.1f}', f'{c.log10_p_value:.1f}',
             f'{c.rms_before_nt:.2f} -> {_nt(c.rms_after_nt)}',
             '' if c.vector_rms_before_nt is None else
             f'{c.vector_rms_before_nt:.2f} -> {_nt(c.vector_rms_after_nt)}',
             '' if c.cv_rms_before_nt is None else
             f'{c.cv_rms_before_nt:.2f} -> {c.cv_rms_after_nt:.2f}',
             '' if c.explained_fraction is None else f'{c.explained_fraction:.0%}',
             'yes' if c.significant else '', c.method] for c in diagnosis.candidates]


CANDIDATE_HEADER = ['effect', 'k', 'delta BIC', 'log10 p', 'scalar RMS (nT)',
                    'vector RMS (nT)', 'held-out RMS (nT)', 'share of excess removed',
                    'significant', 'evidence']

_CSS = """body{font-family:sans-serif;max-width:1300px;margin:1em auto;color:#222}
table{border-collapse:collapse;font-size:13px;margin:0.5em 0}
td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}
th{background:#eee} td:first-child{text-align:left}
pre{background:#f6f6f6;padding:0.6em;font-size:12px;overflow-x:auto}
img{max-width:100%;border:1px solid #ddd;margin:0.3em 0}
.verdict{font-size:1.2em;padding:0.4em;background:#eef6ee;border-left:4px solid #3a3}"""


def _token_sensors(token, n_sensors):
    """Return the sensors (1-based) of an effect token: its ``@j``, else every sensor."""
    m = re.search(r'@(\d+)$', token)
    return {int(m.group(1))} if m else set(range(1, n_sensors + 1))


def _implicated(data, diagnosis, ladder, findings):
    """
    Return what the verdict, the significant candidates, the ladder and the findings point at.

    (Not the candidates that pass the likelihood tests only: one strong missing effect makes
    dozens.)  Returns (tokens, views (the findings' figures), {channel: sensors (1-based)}).
    """
    tokens, views, channels = set(), set(), {}
    if diagnosis is not None:
        tokens.update(c.token for c in diagnosis.candidates if c.significant)
        if diagnosis.verdict_token:
            tokens.add(diagnosis.verdict_token)
    if ladder is not None:
        tokens.update(st.added for st in ladder.steps if st.added)
    everyone = set(range(1, data.n_sensors + 1))
    for f in findings.items:
        views.add(view_of(f))
        if f.token:
            tokens.add(f.token)
        if f.channel:
            channels.setdefault(f.channel, set()).update(
                everyone if f.sensor is None else {f.sensor})
    names = ['temperature', *sorted(data.aux or {}, key=len, reverse=True)]
    for tok in tokens:
        # the longest channel name it contains ('aux_heater' is in 'aux_heater_power')
        ch = next((ch for ch in names if ch in tok), None)
        if ch is not None:
            channels.setdefault(ch, set()).update(_token_sensors(tok, data.n_sensors))
    return tokens, views, channels


#: candidates shown in the page's table; the rest are folded away in a <details>
TOP_CANDIDATES = 10

#: what a figure shows and how to read it, printed under it on the page (view name -> text)
CAPTIONS = {
    'structure': 'Each row one sensor.  Left: the scalar residual |corrected| - |B| over time '
                 "(grey dots) and, in red, what the verdict's term takes out of it (the "
                 'residual without the term minus the residual with it).  Middle: the vector '
                 "residual against sensor 1 (x y z bands) and the term's share (black).  "
                 "Right: the residual in the sensor's own axes (x y z) against what the term "
                 'follows (a channel, the phase of a period, the field rate, a field '
                 'component), the term in black on the sensors it applies to.  Dashed: the '
                 'noise floor.  What is left around the red and black is what the term does '
                 'not explain.',
    'magnitude': 'Measured |raw| (grey) and modelled |A B + o + ...| (blue) magnitude minus '
                 'the reference magnitude |B|, per sensor; each title gives the mean offset '
                 'of the raw readings.  The residual is the small difference between the '
                 'two: see the next figure.',
    'residual_direction': 'The corrected field direction in the sensor frame, Lambert '
                          'equal-area projection about the mean direction (rings 45, 90, '
                          '135 deg from it), coloured by the scalar residual: a pattern is a '
                          'missing linear or non-linear term.',
    'residual_spectrum': 'Power over the white-noise level (dashed line at 1): a line that '
                         'stands out is a periodic disturbance, marked with the effect that '
                         'models it.',
    'change_points': "Each sensor's residual components (x, y, z) averaged over 1 % of the "
                     'record, the segment means between the steps found, and the +-1 sd '
                     'band of that running mean for white noise at the floor.',
    'residual_lagged': 'The residual along the direction it moves with each driving channel, '
                       'against the channel as is (grey) and through the fitted first-order '
                       'lag (red): a lag shows as a loop that closes onto a line; curvature '
                       'that remains is a non-linear coupling.',
}

#: the views drawn only when the diagnosis points at them: name -> what must point at them
SELECTED_VIEWS = {
    'residual_temperature': 'a significant candidate, an adopted effect or a finding '
                            "involving that sensor's temperature",
    'residual_aux': 'a significant candidate, an adopted effect or a finding involving that '
                    'auxiliary channel on that sensor',
    'residual_rate': 'a significant or adopted field_rate candidate',
    'residual_direction': 'a significant or adopted nonlinearity / soft_iron candidate, or '
                          'a direction finding',
    'change_points': 'a step finding or a significant or adopted step candidate',
    'residual_lagged': 'a lag, channel or channel_nonlinear finding',
}


def _unexplained(result, floor, diagnosis, found):
    """Tell whether a residual exceeds :data:`AT_FLOOR_RATIO` x floor and nothing names why."""
    if diagnosis is not None:
        if diagnosis.verdict_token or diagnosis.at_floor:
            return False
    elif all(v <= AT_FLOOR_RATIO * floor.per_sensor_nt[j - 1]
             for j, v in result.scalar_rms_nt.items()):
        return False
    return not any(f.token for f in found.items)


def _sensor_list(sensors):
    return ', '.join(str(j) for j in sorted(sensors))


def _plan(data, result, floor, diagnosis, ladder, found, baseline_m, every):
    """
    Return the report's views in page order: (name, heading, make, why not drawn).

    Unless ``every``, only the :data:`SELECTED_VIEWS` and channel panels something points at.
    """
    tokens, views, channels = _implicated(data, diagnosis, ladder, found)
    everyone = set(range(1, data.n_sensors + 1))
    has_temp = data.temp is not None and bool(np.isfinite(data.temp).any())
    temp_sel = everyone if every else channels.get('temperature', set())
    aux = sorted(data.aux or {})
    aux_sel = {k: (everyone if every else channels[k]) for k in aux if every or k in channels}
    selected = {
        'residual_temperature': bool(temp_sel),
        'residual_aux': bool(aux_sel),
        'residual_rate': any('field_rate' in t for t in tokens) or 'field_rate' in channels,
        'residual_direction': 'residual_direction' in views or any(
            e in t for t in tokens for e in ('nonlinearity', 'soft_iron')),
        'change_points': 'change_points' in views or any(t.startswith('step(') for t in tokens),
        'residual_lagged': 'residual_lagged' in views,
    }
    views = [
        ('structure', 'Residual per sensor: over time and against the driver of the verdict',
         lambda: plot_structure(data, result, floor, diagnosis, adopted_fit(
             data, diagnosis, ladder), found)),
        ('magnitude', 'Measured vs modelled magnitude', lambda: plot_magnitude(data, result)),
        ('residual_time', 'Residual over time', lambda: plot_residual_time(data, result, floor)),
        ('residual_temperature', 'Residual vs temperature',
         None if not has_temp else
         lambda: plot_residual_vs_temperature(data, result, floor, temp_sel)),
        ('residual_aux', 'Residual vs auxiliary channels',
         None if not aux else lambda: plot_residual_vs_aux(data, result, floor, aux_sel)),
        ('residual_rate', 'Residual vs field rate',
         lambda: plot_residual_vs_rate(data, result, floor)),
        ('residual_direction', 'Residual over field direction',
         lambda: plot_direction_map(data, result, floor)),
        ('tensor', 'Gradient tensor before/after',
         None if data.n_sensors != 4 else lambda: plot_tensor(data, result, baseline_m, floor)),
        ('candidates', 'Candidate effects',
         None if diagnosis is None else lambda: plot_candidates(diagnosis)),
        ('ladder', 'Error ladder', None if ladder is None else lambda: plot_ladder(ladder)),
        ('ladder_rungs', 'Error ladder: residual of each rung',
         None if ladder is None else lambda: plot_ladder_rungs(data, ladder)),
        ('residual_spectrum', 'Residual spectrum per sensor',
         lambda: plot_residual_spectrum(found)),
        ('change_points', 'Change points', lambda: plot_change_points(found)),
        ('residual_lagged', 'Residual vs lagged channels',
         lambda: plot_residual_vs_lagged_channels(data, found)),
    ]
    missing = {'residual_temperature': 'the data have no sensor temperature',
               'residual_aux': 'the data have no auxiliary channel',
               'tensor': f'the gradient tensor needs the four-sensor cross '
                         f'({data.n_sensors} sensor(s) here)',
               'candidates': 'no diagnosis', 'ladder': 'no error ladder',
               'ladder_rungs': 'no error ladder'}
    plan = []
    for name, heading, make in views:
        why = (missing[name] if make is None else None if every or selected.get(name, True)
               else f'nothing points at it (drawn for {SELECTED_VIEWS[name]})')
        plan.append((name, heading, None if why else make, why))
    if not every:                                  # the panels left out of drawn views
        rest = [('temperature', temp_sel)] if has_temp and temp_sel else []
        rest += [(k, aux_sel[k]) for k in aux if k in aux_sel]
        for ch, sel in rest:
            if everyone - sel:
                plan.append((None, f'Residual vs {ch}, sensor(s) {_sensor_list(everyone - sel)}',
                             None, f'nothing points at them (drawn for sensor(s) '
                                   f'{_sensor_list(sel)})'))
        others = [k for k in aux if k not in aux_sel]
        if others and aux_sel:
            plan.append((None, f'Residual vs {", ".join(others)}', None,
                         f'nothing points at them (drawn for {SELECTED_VIEWS["residual_aux"]})'))
    return plan


def default_views(data, diagnosis, ladder=None, baseline_m=0.5):
    """Return the views ``write_report`` draws by default: [(name, make() -> Figure or None)]."""
    plan = _plan(data, diagnosis.result, diagnosis.noise_floor, diagnosis, ladder,
                 diagnosis.findings, baseline_m, False)
    return [(name, make) for name, _, make, _ in plan if make is not None]


def write_report(out_dir, data, result=None, diagnosis=None, ladder=None, baseline_m=0.5,
                 title='magcal diagnosis report', figures='relevant', progress=None):
    """
    Write the figures (PNG) and ``index.html`` (self-contained) into ``out_dir``.

    Parameters
    ----------
    out_dir : str or os.PathLike
        Directory (created if missing).
    data : Dataset
        The data of the report (S sensors, N epochs), nT.
    result, diagnosis, ladder : FitResult, Diagnosis, Ladder, optional
        The fit whose residuals are shown (default: the diagnosis' or the ladder's first),
        the diagnosis (candidates, verdict, findings) and the error ladder to show.
    baseline_m : float
        Cross baseline for the tensor figure, m.
    title : str
        Page title.
    figures : {'relevant', 'all'}
        'relevant' (default) draws the views of :data:`SELECTED_VIEWS` only when the
        verdict, a significant candidate, an adopted ladder step or a finding points at
        them (the others listed under "Views not drawn", with the reason); 'all' every view.
    progress : callable, optional
        ``progress('report', i, n, view)`` as the figures are drawn.

    Returns
    -------
    pathlib.Path
        Path of ``index.html``.

    """
    if figures not in ('relevant', 'all'):
        raise ValueError(f"figures must be 'relevant' or 'all', not {figures!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if result is None and diagnosis is None and ladder is None:
        raise ValueError('write_report needs a fit result, a diagnosis or a ladder')
    if result is None:
        result = diagnosis.result if diagnosis is not None else ladder.steps[0].result
    floor = diagnosis.noise_floor if diagnosis is not None else noise_floor_from_data(data, result)
    found = diagnosis.findings if diagnosis is not None else None
    if found is None:
        from magcal_ros.core.discovery.findings import find
        found = find(data, result, baseline_m=baseline_m)
    unexplained = figures != 'all' and _unexplained(result, floor, diagnosis, found)
    every = figures == 'all' or unexplained
    plan = _plan(data, result, floor, diagnosis, ladder, found, baseline_m, every)
    parts = [f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}'
             f'</title><style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>',
             f'<p>data: {html.escape(str(data.meta.get("source", "in memory")))}, '
             f'{data.n_samples} epochs, {data.n_sensors} sensor(s); model '
             f'<b>{html.escape(",".join(compact_spec(result.model)))}</b>; noise floor from '
             f'the data: {floor.value_nt:.2f} nT '
             f'({"; ".join(f"s{j + 1}: " + html.escape(m) for j, m in enumerate(floor.method))}'
             f').</p>']
    red = data.meta.get('reduction')
    if red:
        parts.append(f'<p>A long record: {red["epochs"]} epochs over {red["span_s"]:.0f} s, read '
                     f'in chunks; the fit, the diagnosis and these figures use '
                     f'{red["sample_epochs"]} evenly spread epochs (every '
                     f'{red["sample_stride"]}th), the noise floor {red["noise_blocks"]} '
                     f'contiguous full-rate blocks of {red["noise_block_epochs"]} epochs.</p>')
    if data.meta.get('synthetic_time'):
        parts.append(f'<p>The data have no time column: the time axis is synthetic, at an '
                     f'assumed {data.meta.get("assumed_rate_hz")} Hz.</p>')
    images, skipped, pngs = [], [], []
    with matplotlib.rc_context(RC):          # the figures' text measured and drawn alike
        for i, (name, _, make, _) in enumerate(plan):
            report_progress(progress, 'report', i, len(plan), name)
            fig = None if make is None else make()
            pngs.append(None if fig is None else figure_png(fig))
    report_progress(progress, 'report', len(plan), len(plan), '')
    for (name, heading, _, why), png in zip(plan, pngs):
        if png is None:
            skipped.append((heading, why or 'the data do not allow it (too few epochs)'))
            continue
        (out / f'{name}.png').write_bytes(png)
        caption = (f'<p class="caption">{html.escape(CAPTIONS[name])}</p>'
                   if name in CAPTIONS else '')
        images.append(f'<h2>{html.escape(heading)}</h2>{caption}<img alt="{name}" '
                      f'src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">')
    # the verdict, the residual it explains (the structure), then the evidence
    if diagnosis is not None:
        v = diagnosis.verdict_token
        parts.append(f'<p class="verdict">verdict: <b>{html.escape(v or "none")}</b> — '
                     f'{html.escape(diagnosis.verdict_reason)}</p>')
    if images and images[0].split('<img alt="', 1)[1].startswith('structure"'):
        parts.append(images.pop(0))
    if diagnosis is not None:
        rows = candidate_rows(diagnosis)
        parts.append(f'<h2>Candidate effects: the {min(len(rows), TOP_CANDIDATES)} best</h2>'
                     + _table(rows[:TOP_CANDIDATES], CANDIDATE_HEADER))
        if len(rows) > TOP_CANDIDATES:
            parts.append(f'<details><summary>{len(rows) - TOP_CANDIDATES} more candidates, '
                         'with less evidence</summary>'
                         + _table(rows[TOP_CANDIDATES:], CANDIDATE_HEADER) + '</details>')
        if diagnosis.not_testable:
            parts.append('<p>not testable:</p><ul>' + ''.join(
                f'<li>{html.escape(t)}: {html.escape(r)}</li>'
                for t, r in diagnosis.not_testable) + '</ul>')
        if diagnosis.not_ruled_out:
            parts.append(f'<p>{html.escape(diagnosis.not_ruled_out_text())}</p>')
    parts.append('<h2>Findings (model-free: what is left)</h2>' + (
        _table(finding_rows(found), FINDING_HEADER) if found.items
        else '<p>none: no line, step, lag, trend, attitude pattern, gradient or heavy tail '
             'above the false-alarm and effect-size thresholds</p>'))
    if ladder is not None:
        parts.append('<h2>Error ladder</h2><pre>' + html.escape(ladder.table()) + '</pre>'
                     + f'<p class="verdict">ladder stopped: {html.escape(ladder.reason)}</p>')
    if unexplained:
        parts.append('<p class="views">Every view is drawn: the residual is above the noise '
                     'floor and neither a verdict nor a finding names the cause.</p>')
    parts += images
    if skipped:
        parts.append('<h2>Views not drawn</h2><ul class="omitted">' + ''.join(
            f'<li>{html.escape(heading)}: {html.escape(why)}</li>' for heading, why in skipped)
            + '</ul>' + ('' if every else
                         '<p>Every view: <code>--figures all</code> (<code>magcal diagnose '
                         '--report</code>, <code>magcal report</code>) or '
                         "<code>write_report(..., figures='all')</code>.</p>"))
    if diagnosis is not None:
        parts.append('<details><summary>Summary (as printed by magcal diagnose)</summary><pre>'
                     + html.escape(diagnosis.summary()) + '</pre></details>')
    parts.append('<details><summary>Fit</summary><pre>' + html.escape(result.summary())
                 + '</pre></details>')
    parts.append('</body></html>')
    index = out / 'index.html'
    index.write_text('\n'.join(parts), encoding='utf-8')
    return index
