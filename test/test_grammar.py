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
The model formula: parsing, canonical text, aliases, old calibration files, errors, plug-ins.

Recovery of each coupling x driver from injected data is test_grammar_recovery.py.
"""
import pathlib

import inject_terms as it
import injection as inj
from magcal_ros.cli import _parse_truth, main
from magcal_ros.core import effects as fx
from magcal_ros.core.effects import formula as fm
from magcal_ros.core.effects.base import SensorContext
from magcal_ros.core.model import fit, Model
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, parse_calibration
from magcal_ros.io.csvio import read_csv, write_csv
import numpy as np
import pytest
import yaml

LEGACY = pathlib.Path(__file__).parent / 'data' / 'legacy_cal'

#: FORMULA.md's examples and more: text as a user writes it -> canonical text
FORMULAS = {
    'base + offset(s(t, k=6))@2': 'base + offset(s(t, k=6))@2',
    'base + scale(temperature)@2': 'base + scale(temperature)@2',
    'base + offset(lag(aux_motor))@3': 'base + offset(lag(aux_motor))@3',
    'base + offset(cc(aux_wheel_angle, k=2))': 'base + offset(cc(aux_wheel_angle, k=2))',
    'base + field(s(t, k=8))': 'base + field(s(t, k=8))',
    'base + offset(window(120, 160))@alike': 'base + offset(window(120, 160))@alike',
    'base + offset(temperature * t)@1': 'base + offset(temperature * t)@1',
    'base + drop(120, 160)': 'base + drop(120, 160)',
    'base + drop(120, 160)@2': 'base + drop(120, 160)@2',
    'base + drop(120,160.0)@{3, 1}': 'base + drop(120, 160)@{1,3}',
    'base + drop(120, 160)@{2}': 'base + drop(120, 160)@2',
    'base,temperature@2': 'base + temperature@2',
    'base, step(120,300)@2, periodic(0.23)@3': 'base + step(120,300)@2 + periodic(0.23)@3',
    'offset+soft_iron': 'offset + soft_iron',
    'base,lag(temp),aux_poly(aux_x, 2)@1,aux:x,field_rate,nonlinearity,drift,drift2':
        'base + lag(temperature) + aux_poly(aux_x,2)@1 + aux:aux_x + field_rate + '
        'nonlinearity + drift + drift2',
    'base,site_gradient': 'base + site_gradient',
    'base+offset(rate)@{3, 1}+scale(poly(lin,3))@ 2':
        'base + offset(rate)@{1,3} + scale(poly(lin, 3))@2',
    'base + linear(t) + nonorth(poly(t,2))@each + rotation(sin(0.1000))':
        'base + linear(t) + nonorth(poly(t, 2)) + rotation(sin(0.1))',
    'base + offset(lag(temperature, tau=40))@4 + offset(step(300, 100))':
        'base + offset(lag(temperature, tau=40))@4 + offset(step(100, 300))',
    'base + offset(cc(aux_a, k=1, period=360) * temperature)@{2}':
        'base + offset(cc(aux_a, k=1, period=360) * temperature)@2',
    'base + offset(1)@alike + field(temperature)': 'base + offset(1)@alike + field(temperature)',
    'base + offset(sin(0.050, refine=true))@3': 'base + offset(sin(0.05, refine=true))@3',
}


@pytest.mark.parametrize('text', sorted(FORMULAS))
def test_formula_canonical_text_round_trips(text):
    f = fx.parse(text)
    assert str(f) == FORMULAS[text]
    assert fx.parse(str(f)) == f
    assert fx.parse([t.text for t in f.terms]) == f          # the node's list form


def test_terms_say_what_they_are():
    f = fx.parse('base + offset(s(t, k=6))@2 + field(s(t, k=8)) + '
                 'offset(window(120, 160))@alike + scale(temperature) + temperature@2 + '
                 'offset(lag(aux_motor))@{1,3} + drop(10, 20)')
    base, spl, fld, win, sc, tmp, lag, drop = f.terms
    assert (spl.kind, spl.coupling, spl.driver, spl.scope, spl.signals) == (
        'composed', 'offset', 's(t, k=6)', '2', ('time',))
    # parameters: 3 per column and sensor; the field's 1 per column for the array; the
    # alike window's 3 for every sensor; scale 3 per sensor; lag 3 + tau per sensor
    assert [Model.from_spec([t.text], 4).n_params if t.kind != 'drop' else 0
            for t in f.terms] == [45, 18, 8, 3, 12, 6, 8, 0]
    assert fld.scope == 'array' and win.scope == 'alike' and lag.scope == '{1,3}'
    assert lag.signals == ('time', 'aux_motor') and lag.sensors(4) == [1, 3]
    assert tmp.kind == 'alias' and tmp.expansion == 'offset(temperature)@2 + scale(temperature)@2'
    assert base.expansion == 'offset + scale + nonorthogonality + misalignment'
    assert drop.kind == 'drop' and drop.window == (10.0, 20.0)
    assert f.drops == [(10.0, 20.0, None)]                   # None: every sensor
    m = Model.from_spec(f, 4)
    assert m.drops == [(10.0, 20.0, None)] and m.n_params == 45 + 18 + 8 + 3 + 12 + 6 + 8
    assert Model.from_spec(fx.parse(m.spec()), 4).spec() == m.spec()


#: a bad formula -> words its one-line error must hold (the bad part, what is allowed)
BAD = {
    'base + ofset(t)': ["'ofset(t)'", 'unknown effect', 'offset, rotation, scale'],
    'base + offset(wndow(1, 2))': ["'wndow'", 'window(...)', 'drivers are'],
    'base + offset(s(t, k=1))': ['basis size', '3..20', "'1'"],
    'base + offset(s(t, q=4))': ['unknown option q=', 'k='],
    'base + offset(s(x))': ["'x'", 't, temperature, aux_<channel>, rate'],
    'base + offset(t)@9': ['sensor 9 does not exist', '1..4'],
    'base + offset(t)@somewhere': ['unknown scope @somewhere', '@alike'],
    'base + field(t)@2': ['scope is', 'always the array'],
    'base + linear(rate)': ['per axis', 'offset(...) or scale(...)'],
    'base + offset(step(10)': ['unbalanced'],
    'base + + drift': ['empty term'],
    'base + temperature@alike': ['@alike', 'composed terms'],
    'base + drop(20, 10)': ['must follow its start'],
    'base + drop(1, 2)@each': ['drop takes a sensor scope', '@J or @{J,K}'],
    'base + drop(1, 2)@0': ['sensor 0 does not exist', '1..4'],
    'base + drop(1, 2)@5': ['sensor 5 does not exist', '1..4'],
    'base + drop(1, 2)@{2,7}': ['sensor 7 does not exist', '1..4'],
    'base + offset(poly(t, 9))': ['poly degree', '1..4'],
    'base + offset(sin(-1))': ['sin frequency must be positive'],
    'base + offset(sin(1, refine=maybe))': ['true or false'],
    'base + offset(window(5, 1))': ['the end must follow the start'],
    '': ['empty model'],
}


@pytest.mark.parametrize('text', sorted(BAD))
def test_bad_formula_names_the_bad_part_and_what_is_allowed(text):
    with pytest.raises(ValueError) as err:
        Model.from_spec(text, 4)
    msg = str(err.value)
    for word in BAD[text]:
        assert word in msg, (word, msg)


def test_cli_refuses_a_bad_formula_in_one_line(tmp_path, capsys):
    data = inj.make(n=200, seed=1)
    write_csv(tmp_path / 'd.csv', data)
    code = main(['fit', str(tmp_path / 'd.csv'), '--field-nt', '50000',
                 '--model', 'base + offset(wndow(1, 2))@2'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "'wndow'" in err[0], err


# -- old tokens and old calibration files ------------------------------------------------------

def test_old_calibration_files_load_and_correct_as_written():
    """Files written by the code before the grammar (c43534d) correct to 1e-9 nT as then."""
    data = read_csv(LEGACY / 'data.csv')
    want = np.load(LEGACY / 'corrected.npz')
    assert len(want.files) == 9
    for name in want.files:
        text = (LEGACY / f'{name}.yaml').read_text()
        cal, doc = parse_calibration(text, name)
        got = np.stack([cal.correct(j, data.raw[j - 1], data.context(j))
                        for j in range(1, 5)])[:, ::4]
        np.testing.assert_allclose(got, want[name], rtol=0, atol=1e-9, err_msg=name)
        # the old model list parses to the same model (the old code's spec, written then)
        assert Model.from_spec(doc['model'], 4).spec() == doc['model']


def test_old_tokens_fit_to_the_same_numbers_as_written():
    """
    The old specs refitted give the parameters the old code wrote, to 1e-4 standard error.

    The same maximum of the likelihood: what may differ is where the optimiser stops, which
    moves with its start (the noise estimate's constant 1.4826 became 1/Phi^-1(3/4) after
    the files were written: 1.8e-6 nT on an offset of standard error 0.2 nT, 1e-5 se).
    """
    data = read_csv(LEGACY / 'data.csv')
    for name in ('temperature', 'step_periodic', 'aux'):
        doc = yaml.safe_load((LEGACY / f'{name}.yaml').read_text())
        res = fit(data, ','.join(doc['model']), 50000.0, on_degenerate='flag',
                  check_identifiability=False)
        old = [e['params'][k]['value'] for s in doc['sensors'] for e in s['effects']
               for k in e['params']]
        se = [e['params'][k]['stderr'] for s in doc['sensors'] for e in s['effects']
              for k in e['params']]
        assert np.all(np.abs(res.params - old) <= 1e-4 * np.array(se)), name


#: old token -> the grammar's parts it is evaluated by
TOKEN_PARTS = {
    'temperature': ['offset(temperature)', 'scale(temperature)'],
    'drift': ['offset(t)'],
    'drift2': ['offset(poly(t, 2))'],
    'nonlinearity': ['offset(poly(lin, 3))'],
    'aux:aux_x': ['offset(aux_x)'],
    'aux_poly(aux_x,3)': ['offset(poly(aux_x, 3))'],
    'field_rate': ['offset(rate)'],
    'step(80,150)': ['offset(step(80, 150))'],
    'periodic(0.02)': ['offset(sin(0.02))'],
    'lag(temperature)': ['offset(lag(temperature))'],
}


def test_every_driven_token_is_evaluated_by_its_composition():
    """No token evaluates itself: its change of the reading is its grammar parts' sum."""
    for token, parts in TOKEN_PARTS.items():
        eff = fx.make_effect(token, 1)
        assert isinstance(eff, fx.TokenEffect), token
        assert [p.text for p in eff.parts] == parts, token
        assert type(eff).contribution is fx.TokenEffect.contribution, token
        assert fx.parse(token).terms[0].expansion.startswith(' + '.join(parts)), token
    # every additive effect that ships is a token, but the constant offset (and the array's)
    additive = {n for n in fx.BUILTIN_EFFECTS if fx.effect_class(n).kind == 'additive'}
    assert additive - {'offset'} == {n for n in fx.TOKENS if n != 'aux'}
    assert all(issubclass(fx.effect_class(n), fx.TokenEffect) for n in additive - {'offset'})


# the grammar's terms the tokens are made of, against their formulas written out by hand
# (docs/formulas.md); the tokens themselves against theirs: test/test_effect_golden.py
B = np.array([[20000.0, -5000.0, 45000.0], [-30000.0, 38000.0, 10000.0],
              [1000.0, 2000.0, -49000.0]])                                  # (3, 3) nT
T = np.array([10.0, 10.5, 12.0])                                            # s
TEMP = np.array([20.0, 27.0, 31.0])                                         # degC
CUR = np.array([0.0, 2.0, 5.0])                                             # A
RATE = np.array([[100.0, -50.0, 20.0], [0.0, 300.0, -10.0], [-40.0, 0.0, 80.0]])   # nT/s
V1, V2, V3 = np.array([3.0, -2.0, 1.5]), np.array([0.5, 0.1, -0.4]), np.array([-7.0, 4.0, 2.0])


def _hand_poly(u, *coefs):
    return sum(u[:, None] ** (k + 1) * c if u.ndim == 1 else u ** (k + 1) * c
               for k, c in enumerate(coefs))


#: term -> (parameters, references, raw reading written out by hand)
COMPOSED = {
    'offset(temperature)': (V1, {'temperature0': 25.0}, B + (TEMP - 25.0)[:, None] * V1),
    'scale(temperature)': (V1 * 1e-4, {'temperature0': 25.0},
                           B + (TEMP - 25.0)[:, None] * V1 * 1e-4 * B),
    'offset(t)': (V1, {'t0': 8.0}, B + (T - 8.0)[:, None] * V1),
    # u = (t - mean) / half range: (t - 11) / 2
    'offset(poly(t, 2))': ([*V1, *V2], {'mean': 11.0, 'lo': 9.0, 'hi': 13.0},
                           B + _hand_poly((T - 11.0) / 2.0, V1, V2)),
    'offset(aux_motor_current)': (V1, {'aux_motor_current0': 1.0},
                                  B + (CUR - 1.0)[:, None] * V1),
    'offset(poly(aux_motor_current, 3))': ([*V1, *V2, *V3], {'mean': 2.0, 'lo': 0.0, 'hi': 5.0},
                                           B + _hand_poly((CUR - 2.0) / 2.5, V1, V2, V3)),
    'offset(rate)': (V1 * 1e-3, {}, B + RATE * V1 * 1e-3),
    # per axis u = lin / 50 000 nT, unscaled
    'offset(poly(lin, 3))': ([*V1, *V2, *V3], {}, B + _hand_poly(B / 50000.0, V1, V2, V3)),
    'offset(step(10.2, 11))': ([*V1, *V2], {}, B + (T >= 10.2)[:, None] * V1
                               + (T >= 11.0)[:, None] * V2),
    'offset(sin(0.25))': ([*V1, *V2], {'t0': 9.0},
                          B + np.cos(2 * np.pi * 0.25 * (T - 9.0))[:, None] * V1
                          + np.sin(2 * np.pi * 0.25 * (T - 9.0))[:, None] * V2),
}


@pytest.mark.parametrize('term', sorted(COMPOSED))
def test_composed_term_against_its_formula_by_hand(term):
    params, refs, want = COMPOSED[term]
    m = Model.from_spec(term, 1)
    m.effects[0][0].refs.update(refs)
    ctx = SensorContext(t=T, temp=TEMP, aux={'aux_motor_current': CUR}, raw_rate=RATE)
    np.testing.assert_allclose(m.forward(1, np.asarray(params, float), B, ctx), want,
                               rtol=1e-14, atol=1e-9)


def test_composed_lag_of_a_ramp():
    # tau y' = x - y, x = 2 t (degC), y(0) = x(0) = 0: y = 2 (t - tau + tau e^(-t/tau))
    t = np.arange(0.0, 50.0, 0.5)
    tau, c = 4.0, np.array([1.5, -0.5, 0.2])
    m = Model.from_spec('offset(lag(temperature))', 1)
    m.effects[0][0].refs['mean'] = 30.0
    b = np.tile(B[:1], (len(t), 1))
    y = 2.0 * (t - tau + tau * np.exp(-t / tau))
    got = m.forward(1, np.array([*c, tau]), b, SensorContext(t=t, temp=2 * t))
    np.testing.assert_allclose(got, b + (y - 30.0)[:, None] * c, rtol=1e-12, atol=1e-9)


# -- calibration file and simulator --------------------------------------------------------------

def test_composed_terms_round_trip_through_the_calibration_file():
    formula = ('base + offset(s(t, k=4))@2 + offset(window(100, 140))@alike + '
               'field(sin(0.01)) + scale(temperature)@3 + offset(lag(temperature))@4 + '
               'drop(200, 220) + drop(50, 70)@3')
    data = inj.make(n=1500, seed=2)
    res = fit(data, formula, inj.F_NT, check_identifiability=False, on_degenerate='flag')
    doc = calibration_to_doc(res.calibration)
    cal, doc2 = parse_calibration(dump_calibration(doc), 'composed')
    assert fx.parse(doc2['model']) == fx.parse(res.model.spec())
    assert cal.model.drops == [(200.0, 220.0, None), (50.0, 70.0, (3,))]
    assert 'drop(50, 70)@3' in doc2['model']
    for j in range(1, 5):
        want = res.calibration.correct(j, data.raw[j - 1], data.context(j))
        got = cal.correct(j, data.raw[j - 1], data.context(j))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(cal.params, res.params)


def test_simulate_truth_takes_any_term():
    truth = _parse_truth(['offset(s(t, k=4))@2=1,2,3,4,5,6,7,8,9,10,11,12',
                          'temperature@2=3,-2,1.5,0,0,0', 'field(sin(0.02))=5,3'])
    assert list(truth) == ['offset(s(t, k=4))@2', 'temperature@2', 'field(sin(0.02))']
    from magcal_ros.core.data.simulate import Simulator
    sim = Simulator(truth={'offset(window(1, 2))@alike': [30, -20, 10],
                           'field(sin(0.02))': [5, 3]})
    info = sim.model.param_info()
    got = {(s, lab, nm): v for (s, lab, nm, _), v in zip(info, sim.params)}
    assert got[(0, 'offset(window(1, 2))@alike', 'bz')] == 10
    assert got[(0, 'field(sin(0.02))', 'f_sin')] == 3
    with pytest.raises(ValueError, match='3 values expected'):
        Simulator(truth={'offset(t)@2': [1, 2]})


# -- plug-ins ----------------------------------------------------------------------------------

class SquareWave(fx.Driver):
    """sq(P): a square wave of period P s in time, +-1 (a relay that toggles)."""

    name = 'sq'
    usage = 'sq(<period_s>)'
    signals = ('time',)
    column_names = ('sq',)

    @classmethod
    def from_args(cls, args, kwargs):
        d = cls()
        d.period = float(args[0])
        return d

    @property
    def text(self):
        return f'sq({self.period:g})'

    def columns(self, ctx, lin, refs, q, prefix=''):
        return np.sign(np.sin(2 * np.pi * ctx.t / self.period))[:, None]


class ZOnly(fx.Coupling):
    """An offset along the sensor's z axis only (a coil wound around z)."""

    name = 'zoffset'
    stems = ('bz',)
    unit = 'nT'
    doc = 'offset along z only'

    def contribution(self, y, lin):
        out = np.zeros_like(lin)
        out[:, 2] = y[:, 0]
        return out


@pytest.fixture
def plugins():
    fx.register_driver(SquareWave)
    fx.register_coupling(ZOnly)
    yield
    fx.unregister_driver('sq')
    fx.unregister_coupling('zoffset')


def test_plugin_coupling_and_driver_combine_with_the_builtins(plugins):
    """zoffset(temperature)@3 + offset(sq(20))@2 + zoffset(sq(20))@1, injected by hand."""
    def sq(t):
        return np.sign(np.sin(2 * np.pi * t / 20.0))

    inject = it.combine(
        it.offset(2, lambda t, T, a: np.outer(sq(t), [12.0, -8.0, 5.0])),
        it.offset(3, lambda t, T, a: np.outer(T[2] - T[2].mean(), [0.0, 0.0, 2.0])),
        it.offset(1, lambda t, T, a: np.outer(sq(t), [0.0, 0.0, -7.0])))
    data = inj.make(n=1500, seed=5, inject=inject)
    formula = 'base + offset(sq(20))@2 + zoffset(temperature)@3 + zoffset(sq(20))@1'
    assert str(fx.parse(formula)) == formula
    res = fit(data, formula, inj.F_NT, check_identifiability=False, on_degenerate='flag')
    got = {(s, lab, nm): (v, e) for (s, lab, nm, _), v, e in
           zip(res.model.param_info(), res.params, res.stderr) if '(' in lab}
    want = {(2, 'offset(sq(20))', 'bx'): 12.0, (2, 'offset(sq(20))', 'by'): -8.0,
            (2, 'offset(sq(20))', 'bz'): 5.0, (3, 'zoffset(temperature)', 'bz'): 2.0,
            (1, 'zoffset(sq(20))', 'bz'): -7.0}
    assert set(got) == set(want)
    for k, v in want.items():
        # a +-1 column over 1500 epochs: se about 3 nT / sqrt(1500) = 0.08 nT (the fit's
        # own stderr is used); 5 standard errors allowed
        assert abs(got[k][0] - v) < 5 * got[k][1], (k, got[k], v)
    assert np.all(np.abs(res.sigma_nt - 3.0) < 0.3), res.sigma_nt


def test_plugin_names_cannot_shadow_builtins():
    with pytest.raises(ValueError, match='already registered'):
        fx.register_driver(type('S2', (fx.Driver,), {'name': 's'}))
    with pytest.raises(ValueError, match='built-in'):
        fx.unregister_coupling('offset')
    with pytest.raises(TypeError):
        fx.register_coupling(SquareWave)
    assert fm.parse('offset(1)').terms[0].coupling == 'offset'


@pytest.fixture
def grammar_example(monkeypatch):
    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).resolve().parents[1] / 'examples'))
    names = fx.load_plugin('my_grammar')
    yield names
    fx.unregister_driver('relay')
    fx.unregister_coupling('zoffset')
    import sys
    sys.modules.pop('my_grammar', None)


def test_example_grammar_plugin(grammar_example):
    """examples/my_grammar.py (docs/plugins.md): zoffset(relay(...))@2 on a hand-written relay."""
    assert sorted(grammar_example) == ['relay', 'zoffset']
    code = (pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'plugins.md').read_text()
    snippet = code[code.index("load_plugin('my_grammar')"):].split('```')[0]
    ns = {'load_plugin': fx.load_plugin, 'parse': fx.parse, 'Model': Model}
    exec(snippet, ns)                  # noqa: S102 - the documentation's own snippet
    assert Model.from_spec([ns['f'].terms[1].text], 4).n_params == 1

    def inject(t, temp, aux, b):
        on = (aux['aux_motor_current'] > 4).astype(float)
        return {2: np.outer(on, [0.0, 0.0, 9.0])}
    data = inj.make(n=1500, seed=6, inject=inject)
    formula = 'base + zoffset(relay(aux_motor_current, threshold=4))@2 + offset(s(t, k=4))@3'
    res = fit(data, formula, inj.F_NT, check_identifiability=False, on_degenerate='flag')
    i = [k for k, info in enumerate(res.model.param_info()) if info[1].startswith('zoffset')]
    assert len(i) == 1
    # a 0/1 column switched about half the time: se about 2 x 3 nT / sqrt(1500) = 0.15 nT
    assert abs(res.params[i[0]] - 9.0) < 5 * res.stderr[i[0]], (res.params[i[0]], res.stderr[i])
    cal, _ = parse_calibration(dump_calibration(calibration_to_doc(res.calibration)), 'p')
    np.testing.assert_array_equal(cal.params, res.params)


def test_one_sample_at_a_time_corrects_as_the_whole_record():
    """Live correction sees one sample per call: the drivers' references come from refs."""
    formula = ('base + offset(s(t, k=5))@2 + scale(temperature)@3 + offset(window(50, 90))@alike'
               ' + offset(cc(aux_motor_current, k=1, period=10) * t)@4 + offset(poly(t, 3))@1'
               ' + rotation(sin(0.02))@2 + scale(poly(lin, 2))@1')
    data = inj.make(n=600, seed=7)
    res = fit(data, formula, inj.F_NT, check_identifiability=False, on_degenerate='flag')
    cal, _ = parse_calibration(dump_calibration(calibration_to_doc(res.calibration)), 'live')
    for j in range(1, 5):
        ctx = data.context(j)
        whole = cal.correct(j, data.raw[j - 1], ctx)
        for k in (0, 137, 311, 599):
            one = SensorContext(t=ctx.t[k:k + 1], temp=ctx.temp[k:k + 1],
                                aux={a: v[k:k + 1] for a, v in ctx.aux.items()})
            np.testing.assert_allclose(cal.correct(j, data.raw[j - 1][k:k + 1], one),
                                       whole[k:k + 1], rtol=0, atol=1e-9)


def test_node_model_parameter_takes_formula_terms():
    """The calibration node's ``model`` (a list of terms) is checked by the same parser."""
    from magcal_ros.ros.params import model_check
    check = model_check(4)
    assert check(['base', 'offset(s(t, k=6))@2', 'field(s(t, k=8))', 'drop(120, 160)']) is None
    assert check(['base + offset(window(120, 160))@alike']) is None
    msg = check(['base', 'offset(s(t, k=60))@2'])
    assert 'basis size' in msg and '3..20' in msg, msg


def test_times_on_a_1970_clock_keep_their_milliseconds():
    # a ROS stamp is ~1.8e9 s: 6 significant digits put step(1795889560.9) 500 s off and made
    # a 10 s window end before it starts (the live loop demo's diagnose, 2026-11-28)
    t0 = 1795889560.905
    term = fx.formula.parse(f'base + offset(window({t0}, {t0 + 10.2}))@2').terms[-1]
    assert term.text == 'offset(window(1795889560.905, 1795889571.105))@2'
    assert fx.formula.parse('step(1795889560.9)@1').terms[0].text == 'step(1795889560.9)@1'
    # the search's window driver at such times: the indicator of its 102 samples, centred
    from magcal_ros.core.discovery.bases import time_drivers
    t = t0 - 5.0 + 0.1 * np.arange(300)
    (drv,) = [d for d in time_drivers(t, windows=[(t0, t0 + 10.2)])
              if d.text.startswith('window(')]
    inside = ((t >= t0) & (t <= t0 + 10.2)).astype(float)
    np.testing.assert_allclose(drv.columns(1)[:, 0], inside - inside.mean(), atol=1e-12)
    # small values keep the 6 significant digits of the canonical text
    (term,) = fx.formula.parse('offset(sin(0.233751234))@1').terms
    assert term.text == 'offset(sin(0.233751))@1'
