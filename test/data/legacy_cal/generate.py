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
How the files of this folder were written: by the code before the formula grammar.

Run once at commit c43534d (``git worktree add /tmp/old c43534d``, then
``PYTHONPATH=/tmp/old python generate.py OUTDIR``): a simulated 4 x 300 record (data.csv),
nine calibrations of the old tokens (``<name>.yaml``) and the corrected readings of every
4th epoch (corrected.npz).  test/test_grammar.py checks that today's code loads those
files and corrects to 1e-9 nT as they were then.  The imports are the paths of that commit.
"""
import sys

from magcal_ros.core.model import fit, Model
from magcal_ros.core.simulate import simulate
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, load_calibration
from magcal_ros.io.csvio import read_csv, write_csv
from magcal_ros.pipeline import cross_geometry
import numpy as np

MODELS = {
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


def main(out):
    """Write data.csv, the nine calibration files and corrected.npz into ``out``."""
    data, _ = simulate(n_samples=300, rate_hz=2.0, trajectory='smooth', seed=5, attitude=True)
    write_csv(f'{out}/data.csv', data, comment='legacy calibration test data (magcal simulate)')
    data = read_csv(f'{out}/data.csv')
    corr = {}
    for name, spec in MODELS.items():
        res = fit(data, Model.from_spec(spec, 4), 50000.0, on_degenerate='flag',
                  check_identifiability=False)
        doc = calibration_to_doc(res.calibration, geometry=cross_geometry(),
                                 provenance={'samples': 400})   # as written (sic: 300)
        doc['provenance']['created'] = '2026-11-26T00:00:00+00:00'
        with open(f'{out}/{name}.yaml', 'w') as fh:
            fh.write(dump_calibration(doc))
        cal = load_calibration(f'{out}/{name}.yaml')
        corr[name] = np.stack([cal.correct(j, data.raw[j - 1], data.context(j))
                               for j in range(1, 5)])[:, ::4]
    np.savez_compressed(f'{out}/corrected.npz', **corr)


if __name__ == '__main__':
    main(sys.argv[1])
