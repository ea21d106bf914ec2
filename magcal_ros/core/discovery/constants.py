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

"""Thresholds and defaults of the model diagnosis (every stage reads them here)."""
#: family-wise significance level of the likelihood-ratio tests (Bonferroni over candidates)
ALPHA = 0.01
#: delta BIC a candidate must beat (Kass & Raftery: < -10 is very strong evidence)
MIN_DELTA_BIC = -10.0
#: "at the noise floor": every residual RMS within this ratio of its floor (the diagnosis,
#: the formula search and the findings' effect size)
AT_FLOOR_RATIO = 1.10
#: a finding's model must remove at least this many noise variances (pooled per component):
#: alone it lifts the RMS above AT_FLOOR_RATIO x the floor
MIN_SIGNAL_RATIO = AT_FLOOR_RATIO ** 2 - 1.0
#: folds of the cross-validation (each made of interleaved contiguous blocks: time_blocks)
DEFAULT_FOLDS = 3
#: contiguous blocks per fold, interleaved over the record (time_blocks)
BLOCKS_PER_FOLD = 4
#: shortest block, epochs (the cross-validation needs folds x this many epochs)
MIN_BLOCK = 12
#: practical significance: a verdict must remove at least this share of the excess mean
#: square over the noise floor (held-out; in-sample without cross-validation): each rung
#: removes a visible part of what is left, and effects that only shave the noise are not
#: adopted however significant.  The likelihood tests grow with N, this share does not.
MIN_EXPLAINED = 0.2
#: candidates refitted in full after the one-step screening
DEFAULT_MAX_REFIT = 4
#: iterations of a candidate's refit, from the one-step solution (a lag's time constant
#: from the best point of LAG_GRID_POINTS): a well-posed candidate converges in 2-5; the
#: cap stops a parameter the data do not fix (the time constant of the all-sensors lag on
#: the sensors without one) from wandering
REFIT_MAX_NFEV = 6
#: a refit the cap stopped while it still lowered chi-square, and which passes the likelihood
#: tests, goes on to this many: candidates are compared converged (a pump current whose
#: refit started from a base far off stopped at the cap, behind a sinusoid that had
#: converged, and the sinusoid was named)
REFIT_MORE_NFEV = 30
#: precision of a candidate's refit in chi-square: its iterations stop when one lowers
#: chi-square by less than this.  The tests read chi-square differences against thresholds
#: of order 10; a tenth of a unit moves log10 p by about 0.02 and delta BIC by 0.1
REFIT_CHI2_TOL = 0.1
#: evidence equal within this (chi-square units, the refits' precision) is a tie, broken by
#: parsimony rather than by floating-point rounding (run.order_by_evidence)
EVIDENCE_TIE = REFIT_CHI2_TOL
#: a candidate whose score test (the chi-square decrease its one Gauss-Newton step predicts,
#: exact for effects that enter linearly) gives a delta BIC above this is not evaluated
#: further: BIC prefers the model without it, 10 units short of significance (MIN_DELTA_BIC)
SCORE_RULE_OUT_BIC = 0.0
#: a candidate's one Gauss-Newton step that raises chi-square (a nonlinear effect, a step
#: far from the base fit) is halved up to this many times (a damped Gauss-Newton step)
#: before the candidate is left at its start
STEP_HALVINGS = 5
#: time constants (log-spaced, sample interval to a quarter of the record) a lag's refit
#: start is chosen from, each by one linear step (Screen.lag_start)
LAG_GRID_POINTS = 10
#: epochs the candidates are screened, refitted and cross-validated on (evenly spaced), the
#: same cap as the fit's (model.fit max_fit_samples): cost and memory stay flat above it
DEFAULT_MAX_SAMPLES = 20000
#: effects that contain each other (adding one when the other is present duplicates terms)
NESTED = {'drift': ('drift2',), 'drift2': ('drift',)}

#: change points of the residual the formula search makes steps and windows of
SEARCH_CHANGE_POINTS = 4
#: search terms listed among the diagnosis' candidates
SEARCH_LISTED = 10

# -- the residual toolkit (measures.py) -------------------------------------------------------
#: evenly sampled: every interval within this share of the median one (not tighter: stamps
#: on a Unix-epoch clock carry 2e-5 of a 100 Hz interval of float64 rounding; an error of
#: 1e-3 interval moves a line's phase at the Nyquist frequency by pi 1e-3 rad)
EVEN_SAMPLING = 1e-3
#: most complex exponentials (epochs x frequencies) of one Lomb-Scargle periodogram (~1 s);
#: a larger irregular record is regridded onto its median interval and FFT-ed
LS_BUDGET = 4e7
#: a fixed-rate clock read with jitter and samples lost (a live record's arrival stamps): at
#: most this fraction of the intervals outside (1 -+ CLOCK_JITTER) x the median interval
CLOCK_OUTLIERS = 0.05
CLOCK_JITTER = 0.25

# -- the model-free findings (findings.py) ----------------------------------------------------
#: findings per sensor (greedy rounds)
MAX_PER_SENSOR = 4
#: a step is preferred to the best trend when it removes this share of what the trend does
STEP_OVER_TREND = 0.95
#: shortest segment of a step, as a share of the record
MIN_SEGMENT_FRACTION = 0.02
#: excess kurtosis from which tails count as heavy (a Student t with 10 degrees of freedom)
MIN_EXCESS_KURTOSIS = 1.0
#: a finding on another sensor with the same kind and value is the consensus' echo of the
#: faulty sensor's if it removes less than this share of the largest one's mean square (the
#: echo through the median of 3 others is a few per cent, through the mean of 2 a quarter)
ECHO_RATIO = 0.5
#: fewer epochs than this: no search (the tests' null distributions are asymptotic)
MIN_EPOCHS = 200
#: lag time constants tried per channel
N_TAU = 24
#: half width, in independent frequencies, of the neighbourhood a line is compared with
LINE_NEIGHBOURHOOD = 50
