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

"""Diagnosis report (magcal_ros.report): figures, labels, floor lines, self-contained HTML."""
import base64
import html
import io
import re

from magcal_ros import report
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.discovery import diagnose, ladder
from magcal_ros.core.model import fit
from matplotlib.image import imread
import numpy as np
import pytest

F = 50000.0
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def case():
    # a hidden motor-current coupling on sensor 3 (4 x the 3 nT floor), 2000 samples at 10 Hz
    data, _ = simulate(n_samples=2000, rate_hz=10.0, trajectory='smooth', seed=12,
                       truth={'aux:aux_motor_current@3': [12.0, -6.0, 8.0]})
    lad = ladder(data, 'base', field_nt=F)
    return data, lad


def _labelled(fig, units=True):
    """Every axes with data has a title or suptitle and x/y labels (units in brackets)."""
    for ax in fig.axes:
        if not ax.axison or ax.get_label() == '<colorbar>':
            continue
        # stacked panels sharing the time axis label it once, at the bottom
        xlabel = ax.get_xlabel() or next((o.get_xlabel() for o in
                                          ax.get_shared_x_axes().get_siblings(ax)
                                          if o.get_xlabel()), '')
        assert xlabel and ax.get_ylabel(), ax.get_title()
        if units:
            assert re.search(r'\(.+\)', xlabel) and re.search(r'\(.+\)', ax.get_ylabel())
    assert fig.get_suptitle() or all(ax.get_title() for ax in fig.axes if ax.axison)


def _has_floor_line(fig):
    return any('noise floor' in (ln.get_label() or '') for ax in fig.axes
               for ln in ax.get_lines())


def test_figures_labelled_with_floor(case):
    data, lad = case
    res = lad.steps[0].result
    floor = lad.steps[0].diagnosis.noise_floor
    for fn in (report.plot_residual_time, report.plot_residual_vs_temperature,
               report.plot_residual_vs_aux, report.plot_residual_vs_rate):
        fig = fn(data, res, floor)
        _labelled(fig)
        assert _has_floor_line(fig), fn.__name__
    for fig in (report.plot_magnitude(data, res), report.plot_direction_map(data, res, floor),
                report.plot_tensor(data, res)):
        _labelled(fig)
    # bar charts: one axis is categorical (effect names, ladder steps)
    _labelled(report.plot_ladder(lad), units=False)
    _labelled(report.plot_candidates(lad.steps[0].diagnosis), units=False)
    _labelled(report.plot_ladder_rungs(data, lad))
    assert _has_floor_line(report.plot_ladder(lad))
    # one panel per (aux channel, sensor)
    assert len([a for a in report.plot_residual_vs_aux(data, res, floor).axes
                if a.axison]) == 3 * 4


def test_figures_absent_without_their_data(case):
    data, lad = case
    one = data.subset(np.arange(data.n_samples))
    one.raw = one.raw[:1]
    one.temp = None
    one.aux = {}
    res = fit(one, 'base', field_nt=F)
    floor = lad.noise_floor
    assert report.plot_residual_vs_temperature(one, res, floor) is None
    assert report.plot_residual_vs_aux(one, res, floor) is None
    assert report.plot_tensor(one, res) is None
    assert report.plot_magnitude(one, res) is not None


def test_write_report_self_contained(case, tmp_path):
    data, lad = case
    index = report.write_report(tmp_path / 'rep', data, diagnosis=lad.steps[0].diagnosis,
                                ladder=lad, figures='all')
    text = index.read_text()
    names = ('structure', 'magnitude', 'residual_time', 'residual_temperature', 'residual_aux',
             'residual_rate', 'residual_direction', 'tensor', 'candidates', 'ladder',
             'ladder_rungs', 'residual_spectrum', 'change_points', 'residual_lagged')
    imgs = re.findall(r'<img alt="(\w+)" src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert [n for n, _ in imgs] == list(names)
    for name, b64 in imgs:
        png = base64.b64decode(b64)
        assert png.startswith(PNG_MAGIC)
        assert png == (tmp_path / 'rep' / f'{name}.png').read_bytes()
        h, w = imread(io.BytesIO(png)).shape[:2]
        assert h > 200 and w > 400
    # nothing fetched from elsewhere
    assert not re.search(r'(src|href)="(?!data:)', text)
    assert 'verdict: <b>aux:aux_motor_current@3</b>' in text
    assert 'Error ladder' in text and '+ aux:aux_motor_current@3' not in text  # table text
    assert 'aux:aux_motor_current@3' in lad.table()
    # the ladder's final reason is printed, and every rung's model has its residual panel
    assert f'ladder stopped: {html.escape(lad.reason)}' in text
    assert lad.reason.startswith('verdict none')
    rungs = report.plot_ladder_rungs(data, lad)
    titles = [a.get_title(loc='left') for a in rungs.axes]
    assert len(titles) == len(lad.steps)
    assert titles[0].startswith('rung 0: start: base')
    for i, st in enumerate(lad.steps[1:], start=1):
        assert titles[i].startswith(f'rung {i}: + {st.added}')


def _omitted(text):
    """Return the "Views not drawn" items of a report page: {heading: reason}."""
    block = re.search(r'<h2>Views not drawn</h2><ul class="omitted">(.*?)</ul>', text)
    items = re.findall(r'<li>(.*?)</li>', block.group(1)) if block else []
    return dict(html.unescape(i).split(': ', 1) for i in items)


def test_report_draws_the_views_the_diagnosis_points_at(case, tmp_path):
    # the hidden effect is the motor current on sensor 3 (injected by the case): the default
    # report draws the residual against that channel for that sensor only, and says which
    # views and panels it left out and why
    data, lad = case
    index = report.write_report(tmp_path, data, diagnosis=lad.steps[0].diagnosis, ladder=lad)
    text = index.read_text()
    drawn = re.findall(r'<img alt="(\w+)"', text)
    always = ['structure', 'magnitude', 'residual_time', 'tensor', 'candidates', 'ladder',
              'ladder_rungs', 'residual_spectrum']
    assert [n for n in drawn if n in always] == always
    assert 'residual_aux' in drawn
    for name in ('residual_temperature', 'residual_rate', 'residual_direction',
                 'change_points'):
        assert name not in drawn and not (tmp_path / f'{name}.png').exists()
    aux = report.plot_residual_vs_aux(data, lad.steps[0].result, lad.noise_floor,
                                      {'aux_motor_current': {3}})
    assert [a.get_title() for a in aux.axes] == ['sensor 3 vs aux_motor_current']
    why = _omitted(text)
    for heading in ('Residual vs temperature', 'Residual vs field rate',
                    'Residual over field direction', 'Change points'):
        assert why[heading].startswith('nothing points at it (drawn for '), heading
    assert why['Residual vs aux_motor_current, sensor(s) 1, 2, 4'] == (
        'nothing points at them (drawn for sensor(s) 3)')
    assert why['Residual vs aux_heater_power, aux_pump_current'].startswith(
        'nothing points at them')
    assert '--figures all' in text
    # every view: nothing left out for want of relevance, only what the data lack
    full = report.write_report(tmp_path / 'all', data, diagnosis=lad.steps[0].diagnosis,
                               ladder=lad, figures='all').read_text()
    assert _omitted(full) == {}
    with pytest.raises(ValueError, match="'relevant' or 'all'"):
        report.write_report(tmp_path, data, diagnosis=lad.steps[0].diagnosis, figures='some')


def test_report_opens_with_the_structure_then_ten_candidates(case, tmp_path):
    # issue 18, item 5: the verdict, the residual it explains, the ten best candidates (the
    # rest folded away), then the findings and the other views
    data, lad = case
    diag = lad.steps[0].diagnosis
    text = report.write_report(tmp_path, data, diagnosis=diag, ladder=lad).read_text()
    order = [text.index(m) for m in (
        'class="verdict"', '<img alt="structure"', '<h2>Candidate effects: the 10 best</h2>',
        f'<details><summary>{len(diag.candidates) - 10} more candidates',
        '<h2>Findings', '<img alt="magnitude"', '<h2>Views not drawn</h2>',
        '<details><summary>Summary')]
    assert order == sorted(order)
    assert len(diag.candidates) > 10
    top = re.search(r'the 10 best</h2><table>(.*?)</table>', text).group(1)
    rows = re.findall(r'<tr><td>(.*?)</td>', top)
    assert rows == [c.token for c in diag.candidates[:10]]
    folded = re.search(r'more candidates, with less evidence</summary><table>(.*?)</table>',
                       text).group(1)
    assert re.findall(r'<tr><td>(.*?)</td>', folded) == [c.token for c in diag.candidates[10:]]


def test_structure_draws_the_adopted_term_over_the_residual(case):
    # the verdict couples the motor current into sensor 3: its row shows the scalar residual
    # over time with the term's fit (base residual minus the residual with the term), the
    # vector residual, and the residual against the motor current
    data, lad = case
    diag = lad.steps[0].diagnosis
    base, adopted = diag.result, lad.steps[1].result
    assert lad.steps[1].added == diag.verdict_token == 'aux:aux_motor_current@3'
    fig = report.plot_structure(data, base, diag.noise_floor, diag, adopted, diag.findings)
    axes = np.array(fig.axes).reshape(4, 3)
    t = data.t - data.t[0]
    term = base.scalar_residual_nt[2] - adopted.scalar_residual_nt[2]
    (line,) = [ln for ln in axes[2, 0].get_lines()
               if ln.get_label().startswith('fit of aux:aux_motor_current@3')]
    x, y = line.get_data()
    k = np.searchsorted(t, x)
    assert np.allclose(y, term[k])
    # the term takes out the excess: base residual = term + white noise at the floor, so
    # its RMS is sqrt(RMS_before^2 - floor^2), to the 10 % the floor is known to over 2000
    # epochs (the floor's own sd is ~2 %, the remaining misfit is below the floor)
    fl = diag.noise_floor.per_sensor_nt[2]
    excess = np.sqrt(base.scalar_rms_nt[3] ** 2 - fl ** 2)
    assert abs(np.sqrt(np.mean(term ** 2)) / excess - 1) < 0.1
    # the sensors without the term: its fit there is far below their floor
    for j in (1, 2, 4):
        other = base.scalar_residual_nt[j - 1] - adopted.scalar_residual_nt[j - 1]
        assert np.sqrt(np.mean(other ** 2)) < 0.2 * diag.noise_floor.per_sensor_nt[j - 1]
    assert axes[2, 2].get_xlabel() == 'aux_motor_current (A)'
    xd = axes[2, 2].get_lines()[0].get_xdata()
    assert np.isin(xd, data.aux['aux_motor_current']).all()
    assert axes[0, 1].axison is False                  # sensor 1: no vector residual
    assert axes[2, 1].get_title(loc='left').startswith('sensor 3 - sensor 1: vector RMS')
    assert 'verdict aux:aux_motor_current@3' in fig.get_suptitle()
    # the driver of other kinds of verdict
    assert np.array_equal(report.verdict_driver(data, 'temperature@2', 2)[2], data.temp[1])
    name, label, phase = report.verdict_driver(data, 'periodic(0.25)@1', 1)
    assert name == 'phase' and np.allclose(phase, (t * 0.25) % 1.0)
    assert report.verdict_driver(data, 'drift@4', 4)[0] == 'time'


def test_write_report_needs_a_result(tmp_path, case):
    data, _ = case
    with pytest.raises(ValueError, match='needs a fit result'):
        report.write_report(tmp_path, data)


def test_report_from_result_only(tmp_path):
    data, _ = simulate(n_samples=600, rate_hz=5.0, trajectory='smooth', seed=2, n_sensors=1,
                       aux=False)
    res = fit(data, 'base', field_nt=F)
    index = report.write_report(tmp_path, data, result=res)
    assert (tmp_path / 'residual_time.png').exists()
    assert not (tmp_path / 'candidates.png').exists()
    assert not (tmp_path / 'tensor.png').exists() and not (tmp_path / 'residual_aux.png').exists()
    # what the data lack is said, not silently skipped
    why = _omitted(index.read_text())
    assert why['Gradient tensor before/after'] == ('the gradient tensor needs the four-sensor '
                                                   'cross (1 sensor(s) here)')
    assert why['Residual vs auxiliary channels'] == 'the data have no auxiliary channel'
    assert 'class="verdict"' not in index.read_text()
    d = diagnose(data, base=res, field_nt=F, folds=0)
    assert report.candidate_rows(d)[0][0] == d.candidates[0].token
