"""Write calibration files and corrected outputs with main's code (run once, before the grammar)."""
import sys
import numpy as np
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.csvio import write_csv, read_csv
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration
from magcal_ros.pipeline import cross_geometry
from magcal_ros.core.model import fit, Model

out = sys.argv[1]
data, sim = simulate(n_samples=300, rate_hz=2.0, trajectory='smooth', seed=5, attitude=True)
write_csv(f'{out}/data.csv', data, comment='legacy calibration test data (magcal simulate)')
data = read_csv(f'{out}/data.csv')
models = {
    'base': 'base',
    'temperature': 'base,temperature@2',
    'drift': 'base,drift,drift2@3',
    'aux': 'base,aux:aux_motor_current@1,aux_poly(aux_heater_power,2)@2',
    'step_periodic': 'base,step(60,120)@2,periodic(0.05)@3',
    'lag': 'base,lag(temperature)@4',
    'rate_nonlin': 'base,field_rate@2,nonlinearity@1',
    'soft_iron': 'offset,soft_iron',
    'site_gradient': 'base,site_gradient',
}
corr = {}
for name, spec in models.items():
    m = Model.from_spec(spec, 4)
    res = fit(data, m, 50000.0, on_degenerate='flag', check_identifiability=False)
    cal = res.calibration
    doc = calibration_to_doc(cal, geometry=cross_geometry(), provenance={'samples': 400})
    doc['provenance']['created'] = '2026-11-26T00:00:00+00:00'
    open(f'{out}/{name}.yaml', 'w').write(dump_calibration(doc))
    from magcal_ros.io.calfile import load_calibration
    cal2 = load_calibration(f'{out}/{name}.yaml')[0] if isinstance(load_calibration(f'{out}/{name}.yaml'), tuple) else load_calibration(f'{out}/{name}.yaml')
    corr[name] = np.stack([cal2.correct(j, data.raw[j - 1], data.context(j)) for j in range(1, 5)])[:, ::4]
    print(name, spec, res.params.size, np.abs(corr[name]).max())
np.savez_compressed(f'{out}/corrected.npz', **corr)
