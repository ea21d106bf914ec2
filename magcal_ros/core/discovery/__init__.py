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

Given rotation data and a fitted model, :func:`diagnose`

1. estimates the sensor noise floor from the data themselves (high-order differences of the
   raw series and of the model's scalar residual, :func:`noise_floor_from_data`), so that
   "the residual is at the noise floor" is a test against an independent number, not
   against the model's own noise estimate;
2. lists every effect that is not in the model (per sensor where it applies, plus each
   auxiliary channel on all sensors at once), and sets aside, with the reason, those the
   data cannot excite (``Effect.check``: no temperature column, a channel that never
   changes, ...);
3. screens every candidate by one Gauss-Newton step of the extended model from the fitted
   parameters (exact for effects that enter linearly, as all driven effects do), and refits
   the most promising ones from there with the full maximum-likelihood fit
   (:func:`magcal_ros.core.model.fit`, warm start, the noise levels fixed at the base fit's
   so that chi-square and BIC are comparable);
4. ranks by evidence: delta BIC, the likelihood-ratio p-value (chi-square with k = added
   parameters) with a Bonferroni correction over the candidates, and the effect size on
   held-out data: k-fold cross-validation whose folds are *interleaved contiguous blocks
   of time* (:func:`time_blocks`: neighbouring samples are correlated, so a random split
   would leak; interleaving means a step or a drift is interpolated, never extrapolated
   from one end; effects with memory keep their state across the blocks), fit on the
   other folds (by default one Gauss-Newton step from the all-data fit with the fold's
   rows removed, which agrees with a full refit to 1e-7 in the held-out RMS:
   :func:`cross_validate`).  The effect size is ``explained_fraction``, the share of the
   excess mean square over the noise floor that the effect removes on held-out data
   (in-sample when ``folds=0`` or the record is too short; the verdict says which);
5. gives a verdict: the best candidate that passes the p-value and BIC tests *and*
   removes at least :data:`MIN_EXPLAINED` of the excess, or ``none`` when the residual is
   within 10 % of the noise floor or no candidate passes.  Besides the catalog, the
   candidates include the offset steps and spectral lines found in the residual
   (:func:`propose_from_residual`: ``step(t)``, ``periodic(f)``), the lags and polynomial
   couplings of each channel, and every effect on all sensors at once.

:func:`ladder` repeats diagnose -> add the verdict -> refit until nothing is missing and

:func:`ladder` repeats diagnose -> add the verdict -> refit until nothing is missing and
tabulates the held-out RMS of each step (the "error ladder").

The package, one module per stage (every name below is importable from here):

- :mod:`.constants`: the thresholds (``ALPHA``, ``MIN_DELTA_BIC``, ``MIN_EXPLAINED``, ...);
- :mod:`.measures`: residual measures (nT), likelihood ratio, explained share;
- :mod:`.candidates`: the tokens to test (catalog, residual, findings), :class:`Candidate`;
- :mod:`.screen`: the one-step Gauss-Newton screening of many candidates;
- :mod:`.validation`: time blocks, cross-validation, the approximate leave-out;
- :mod:`.results`: :class:`Diagnosis`, its JSON form;
- :mod:`.run`: :func:`diagnose`, one function per stage;
- :mod:`.error_ladder`: :func:`ladder`, :class:`Ladder`, :class:`LadderStep`.
"""
# the one noise-floor estimator (fit, diagnose, report, nodes); the old name is kept here
from magcal_ros.core.data.noise import data_noise_floor as noise_floor_from_data, NoiseFloor
from magcal_ros.core.discovery.candidates import (Candidate, candidate_tokens, extend_model,
                                                  propose_from_residual, split_testable,
                                                  token_label, tokens_from_findings)
from magcal_ros.core.discovery.constants import (ALPHA, AT_FLOOR_RATIO, BLOCKS_PER_FOLD,
                                                 DEFAULT_FOLDS, DEFAULT_MAX_REFIT,
                                                 DEFAULT_MAX_SAMPLES, EVIDENCE_TIE, MIN_BLOCK,
                                                 MIN_DELTA_BIC, MIN_EXPLAINED, NESTED,
                                                 REFIT_CHI2_TOL, REFIT_MAX_NFEV,
                                                 SCORE_RULE_OUT_BIC)
from magcal_ros.core.discovery.error_ladder import Ladder, ladder, LadderStep
from magcal_ros.core.discovery.measures import (dof_factor, evaluate_residuals, Evaluation,
                                                explained_share, likelihood_ratio, n_observations,
                                                soft_l1_lr_loss)
from magcal_ros.core.discovery.results import compact_spec, Diagnosis, jsonable
from magcal_ros.core.discovery.run import diagnose
from magcal_ros.core.discovery.screen import Screen
from magcal_ros.core.discovery.validation import cross_validate, time_blocks

__all__ = [
    'ALPHA', 'AT_FLOOR_RATIO', 'BLOCKS_PER_FOLD', 'Candidate', 'DEFAULT_FOLDS',
    'DEFAULT_MAX_REFIT', 'DEFAULT_MAX_SAMPLES', 'Diagnosis', 'EVIDENCE_TIE', 'Evaluation',
    'Ladder', 'LadderStep', 'MIN_BLOCK', 'MIN_DELTA_BIC', 'MIN_EXPLAINED', 'NESTED',
    'NoiseFloor', 'REFIT_CHI2_TOL', 'REFIT_MAX_NFEV', 'SCORE_RULE_OUT_BIC', 'Screen',
    'candidate_tokens', 'compact_spec', 'cross_validate',
    'diagnose', 'dof_factor', 'evaluate_residuals', 'explained_share', 'extend_model',
    'jsonable', 'ladder', 'likelihood_ratio', 'n_observations', 'noise_floor_from_data',
    'propose_from_residual', 'soft_l1_lr_loss', 'split_testable',
    'time_blocks', 'token_label', 'tokens_from_findings',
]
