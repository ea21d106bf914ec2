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
What the report's figures show (issue 10 item 6), tested on the data behind them.

- the direction map has no +-180 deg seam: a cone of directions about -x (where azimuth
  wraps) is one closed ring in the equal-area projection, and the projection is equal-area;
- the magnitude figure with a reference 3 000 nT away states the offset and plots about it;
- the error ladder's legend covers no step;
- the candidates chart plots what decided the verdict (the held-out RMS drop);
- the axis labels, placed once by the report, clear their tick labels by the label pad (as
  matplotlib places them), and no axis makes a tick outside its view;
- the PNG encoder's files decode (with Pillow's decoder) to exactly the pixels given.
The inputs are built here (plain numpy vectors and minimal stand-ins for a fit, a ladder and
a diagnosis), independent of the model code.
"""
import io
from types import SimpleNamespace

from magcal_ros import report
from magcal_ros.core.data.dataset import Dataset
from matplotlib.figure import Figure
from matplotlib.transforms import Bbox
import numpy as np
from PIL import Image


def cone(axis, half_angle_deg, n=720):
    """(n, 3) unit vectors going once round a cone about ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(a, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    h = np.radians(half_angle_deg)
    return (np.cos(h) * a[None] + np.sin(h) * (np.cos(th)[:, None] * e1
                                               + np.sin(th)[:, None] * e2))


def test_direction_projection_has_no_seam_and_is_equal_area():
    u = cone([-1.0, 0.1, 0.2], 40.0)
    az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    assert np.abs(np.diff(az)).max() > 300          # the old map cut this cone in two
    x, y, c = report.direction_projection(u)
    step = np.hypot(np.diff(x), np.diff(y))
    # neighbours on the cone (0.5 deg apart, ~0.009 on the projection) stay neighbours
    assert step.max() < 0.02
    # a cone about the centre is a circle of radius 2 sin(h/2)
    r = np.hypot(x, y)
    np.testing.assert_allclose(r, 2 * np.sin(np.radians(40.0) / 2), rtol=1e-3)
    # equal area: uniform directions fill the disc of radius 2 uniformly, so the fraction
    # within radius R is R^2 / 4 (binomial sd for 20 000 points: 0.0035)
    v = np.random.default_rng(0).normal(size=(20000, 3))
    x, y, _ = report.direction_projection(v, centre=[0.0, 0.0, 1.0])
    for rad in (1.0, np.sqrt(2), 1.8):
        assert abs(np.mean(np.hypot(x, y) < rad) - rad ** 2 / 4) < 0.015


def magnitude_case(n, reference_nt, seed):
    """
    Return one sensor reading a 50 000 nT field +- 20 nT in random directions, and a fit.

    The stand-in fit has the reference magnitude ``reference_nt`` and zero residuals.
    Returns (Dataset, fit, raw (n, 3) nT).
    """
    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    raw = (50000.0 + 20.0 * np.sin(np.arange(n) / 30.0))[:, None] * u
    fit = SimpleNamespace(field_magnitude_nt=np.full(n, reference_nt),
                          residual_nt=np.zeros((1, n, 3)))
    return Dataset(t=np.arange(n) / 10.0, raw=raw[None]), fit, raw


def test_magnitude_figure_states_a_3000_nt_offset_and_plots_about_it():
    data, fit, raw = magnitude_case(500, 47000.0, seed=1)
    expected = float(np.mean(np.linalg.norm(raw, axis=1))) - 47000.0     # 3 000 + mean swing
    assert abs(expected - 3000.0) < 20
    fig = report.plot_magnitude(data, fit)
    ax = fig.axes[0]
    assert f'{expected:+,.0f} nT' in ax.get_title()
    meas = ax.get_lines()[0].get_ydata()
    # about the reference: the 40 nT swing on a 3 000 nT offset, not 47 000 .. 50 000
    assert 2970 < meas.min() and meas.max() < 3030
    lo, hi = ax.get_ylim()
    assert hi - lo < 4000


def _extent(artist, fig):
    return artist.get_window_extent(fig.canvas.get_renderer())


def ladder_case(*steps):
    """Return a stand-in error ladder: steps (held-out RMS nT, effect added), floor 3 nT."""
    return SimpleNamespace(
        steps=[SimpleNamespace(cv_rms_nt=v, residual_rms_nt=v * 0.98, model=('base',),
                               added=tok) for v, tok in steps],
        noise_floor=SimpleNamespace(value_nt=3.0))


def test_ladder_legend_covers_no_step():
    # steps that fall little: the last bar reaches the top right, where the legend sat
    lad = ladder_case((12.0, None), (11.6, 'temperature@2'), (11.2, 'aux:aux_m@3'))
    fig = report.plot_ladder(lad)
    fig.canvas.draw()
    ax = fig.axes[0]
    leg = _extent(ax.get_legend(), fig)
    for artist in list(ax.patches) + list(ax.texts):
        assert not Bbox.intersection(leg, _extent(artist, fig)), artist


def test_candidates_chart_plots_the_share_that_decided():
    # the verdict rests on the held-out share of the excess over the floor (and the likelihood
    # tests), so the bars are that share; delta BIC alone decides nothing
    def cand(tok, dbic, p, share, before, after, sig):
        d = {'token': tok, 'delta_bic': dbic, 'p_value': p, 'explained_fraction': share,
             'cv_rms_before_nt': before, 'cv_rms_after_nt': after, 'significant': sig}
        return SimpleNamespace(to_dict=lambda d=d: dict(d), token=tok)
    diag = SimpleNamespace(
        candidates=(cand('aux:aux_m@3', -80.0, 1e-12, 0.91, 12.0, 3.2, True),
                    cand('temperature@1', -500.0, 1e-40, 0.05, 12.0, 12.4, False),
                    cand('drift@2', 4.0, 0.3, None, None, None, False)),
        verdict_token='aux:aux_m@3', verdict_reason='held-out RMS 12.00 -> 3.20 nT',
        decided_by='held-out share', p_threshold=1e-3)
    rows = report.candidate_chart_data(diag)
    np.testing.assert_allclose([r['held_out_drop_nt'] for r in rows[:2]], [8.8, -0.4])
    assert rows[2]['held_out_drop_nt'] is None
    assert [r['verdict'] for r in rows] == [True, False, False]
    # temperature@1: the strongest delta BIC passes the likelihood tests but removes 5 %
    assert [r['likelihood_tests'] for r in rows] == [True, True, False]
    fig = report.plot_candidates(diag)
    widths = [p.get_width() for p in fig.axes[0].patches]
    np.testing.assert_allclose(widths, [0.91, 0.05, 0.0])
    # the verdict's bar is the outlined one: a large delta BIC alone does not decide
    assert [p.get_linewidth() for p in fig.axes[0].patches][0] == 2
    assert 'held-out share' in fig.axes[0].get_xlabel()
    assert 'verdict: aux:aux_m@3' in fig.get_suptitle()


def test_axis_labels_clear_the_tick_labels_by_the_label_pad():
    # y tick labels of six characters ('−12020', a reference 12 000 nT above the field),
    # two-line x tick labels ('start:\nbase', 8 pt): each axis label sits the label pad
    # (4 pt) below / left of the outermost tick label, to a pixel
    data, fit, _ = magnitude_case(400, 62000.0, seed=2)
    lad = ladder_case((12.0, None), (6.0, 'temperature@2'))
    checked = 0
    for fig in (report.plot_magnitude(data, fit), report.plot_ladder(lad)):
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        for ax in fig.axes:
            for axis, below in ((ax.xaxis, True), (ax.yaxis, False)):
                lo, hi = sorted(axis.get_view_interval())
                locs = axis.get_majorticklocs()
                slack = 1e-9 * (hi - lo)
                assert np.all((locs >= lo - slack) & (locs <= hi + slack)), (locs, lo, hi)
                labels = [t.label1 for t in axis.get_major_ticks()[:len(locs)]
                          if t.label1.get_visible() and t.label1.get_text()]
                if not axis.label.get_text() or not labels:
                    continue
                box = axis.label.get_window_extent(renderer)
                ticks = [t.get_window_extent(renderer) for t in labels]
                gap = (min(b.y0 for b in ticks) - box.y1 if below
                       else min(b.x0 for b in ticks) - box.x1)
                assert abs(gap - axis.labelpad * fig.dpi / 72.0) < 1.0, (axis.label, gap)
                checked += 1
    assert checked == 4
    assert any('\n' in t.get_text() for t in fig.axes[0].get_xticklabels())
    assert any(len(t.get_text()) == 6 for t in report.plot_magnitude(data, fit).axes[0]
               .get_yticklabels())


def test_report_png_is_the_canvas_pixels():
    # the report's PNG (Pillow's encoder) decodes to the canvas's pixels, opaque, RGB
    fig = Figure(figsize=(3, 2), dpi=report.DPI)
    report.FigureCanvasAgg(fig)
    fig.add_subplot().plot([0, 1, 3], [2, -1, 5], 'o-')
    png = report.figure_png(fig)
    rgba = np.asarray(fig.canvas.buffer_rgba())
    assert (rgba[..., 3] == 255).all()
    assert png.startswith(b'\x89PNG\r\n\x1a\n')
    with Image.open(io.BytesIO(png)) as back:
        assert back.mode == 'RGB'
        np.testing.assert_array_equal(np.asarray(back), rgba[..., :3])
