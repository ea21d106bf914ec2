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
Model diagnosis: compare a fitted model with the measurements and name what is missing.

:func:`diagnose` estimates the noise floor from the data (:func:`noise_floor_from_data`),
lists every effect not in the model and the residual's steps and lines, sets aside those the
data cannot excite, screens every candidate by one Gauss-Newton step and refits the best,
ranks them by delta BIC, the likelihood-ratio p-value (Bonferroni) and the share of the
excess over the floor they remove held out (:func:`cross_validate`, :func:`time_blocks`),
and gives a verdict: the best that passes all three (at least :data:`MIN_EXPLAINED`), or
``none``.  :func:`ladder` repeats diagnose -> add the verdict -> refit (the error ladder).
One module per stage (docs/design.md); every name below is importable from here.
"""
from magcal_ros.core.data.noise import data_noise_floor as noise_floor_from_data
from magcal_ros.core.discovery.candidates import (Candidate, candidate_tokens, extend_model,
                                                  propose_from_residual, tokens_from_findings)
from magcal_ros.core.discovery.constants import (AT_FLOOR_RATIO, EVIDENCE_TIE, MIN_DELTA_BIC,
                                                 MIN_EXPLAINED, SCORE_RULE_OUT_BIC)
from magcal_ros.core.discovery.error_ladder import Ladder, ladder, LadderStep
from magcal_ros.core.discovery.measures import (evaluate_residuals, Evaluation,
                                                likelihood_ratio, n_observations,
                                                soft_l1_lr_loss)
from magcal_ros.core.discovery.results import compact_spec, Diagnosis, jsonable
from magcal_ros.core.discovery.run import diagnose
from magcal_ros.core.discovery.screen import Screen
from magcal_ros.core.discovery.validation import cross_validate, time_blocks

__all__ = [
    'AT_FLOOR_RATIO', 'Candidate', 'Diagnosis', 'EVIDENCE_TIE', 'Evaluation', 'Ladder',
    'LadderStep', 'MIN_DELTA_BIC', 'MIN_EXPLAINED', 'SCORE_RULE_OUT_BIC', 'Screen',
    'candidate_tokens', 'compact_spec', 'cross_validate', 'diagnose', 'evaluate_residuals',
    'extend_model', 'jsonable', 'ladder', 'likelihood_ratio', 'n_observations',
    'noise_floor_from_data', 'propose_from_residual', 'soft_l1_lr_loss', 'time_blocks',
    'tokens_from_findings',
]
