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

"""What is fitted (:mod:`.spec`) and how (:mod:`.fitting`): the names other packages import."""
from magcal_ros.core.model.calibration import Calibration
from magcal_ros.core.model.fitting import (DegenerateDataError, evaluate, fit, fit_epochs,
                                           FitResult, initial_params, priors_for)
from magcal_ros.core.model.spec import data_hash, Model

__all__ = ['Calibration', 'data_hash', 'DegenerateDataError', 'evaluate', 'fit', 'fit_epochs',
           'FitResult', 'initial_params', 'Model', 'priors_for']
