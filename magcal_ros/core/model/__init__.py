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
The model and its engine: what is fitted, and how.

- :mod:`.spec`: :class:`Model`, the effects of every sensor with a flat parameter vector;
- :mod:`.engine`: the profiled (variable-projection) least-squares problem;
- :mod:`.solvers`: Levenberg-Marquardt, covariances;
- :mod:`.fitting`: :func:`fit`, :class:`FitResult`, :func:`evaluate` (maximum likelihood,
  paper 004's closed form as the start);
- :mod:`.calibration`: :class:`Calibration`, a fit made ready for live correction;
- :mod:`.identifiability`: what the data can determine (with
  :mod:`magcal_ros.core.geometry.coverage`);
- :mod:`.planar`, :mod:`.plausibility`, :mod:`.site_gradient`: a turn about one axis,
  parameters no real sensor has, the site gradient's report and bounds;
- :mod:`.paper_methods`: the closed forms of :mod:`magcal_ros.core.papers` (papers 000
  and 002) written as a :class:`Calibration` (``magcal fit --method sine|reference``);
- :mod:`.notes`: structured warnings.

The names most code needs are importable from here
(``from magcal_ros.core.model import fit, FitResult, Calibration, Model``); modules inside
the package import each other directly, never through this facade.
"""
from magcal_ros.core.model.calibration import Calibration
from magcal_ros.core.model.fitting import (DegenerateDataError, evaluate, fit, fit_epochs,
                                           FitResult, initial_params, priors_for)
from magcal_ros.core.model.spec import data_hash, Model

__all__ = ['Calibration', 'data_hash', 'DegenerateDataError', 'evaluate', 'fit', 'fit_epochs',
           'FitResult', 'initial_params', 'Model', 'priors_for']
