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
#: "at the noise floor": every residual RMS within this ratio of its floor
AT_FLOOR_RATIO = 1.10
#: noise variances a finding's model must remove (alone: the RMS above AT_FLOOR_RATIO x floor)
MIN_SIGNAL_RATIO = AT_FLOOR_RATIO ** 2 - 1.0
#: folds of the cross-validation (each made of interleaved contiguous blocks: time_blocks)
DEFAULT_FOLDS = 3
#: contiguous blocks per fold, interleaved over the record (time_blocks)
BLOCKS_PER_FOLD = 4
#: shortest block, epochs (the cross-validation needs folds x this many epochs)
MIN_BLOCK = 12
#: practical significance: a verdict removes at least this share of the excess mean square
#: over the floor (held-out, else in-sample); the likelihood tests grow with N, this does not
MIN_EXPLAINED = 0.2
#: candidates refitted in full after the one-step screening
DEFAULT_MAX_REFIT = 4
#: iterations of a candidate's refit from the one-step solution (well-posed: 2-5); the cap
#: stops a parameter the data do not fix from wandering
REFIT_MAX_NFEV = 6
#: a capped refit that passes the likelihood tests goes on to this many, so that candidates
#: are compared converged (a pump current stopped at the cap behind a sinusoid)
REFIT_MORE_NFEV = 30
#: precision of a candidate's refit in chi-square (the tests' thresholds are of order 10)
REFIT_CHI2_TOL = 0.1
#: evidence equal within this (chi-square units, the refits' precision) is a tie, broken by
#: parsimony rather than by floating-point rounding (run.order_by_evidence)
EVIDENCE_TIE = REFIT_CHI2_TOL
#: a candidate whose score test (its one step's predicted chi-square decrease) gives a delta
#: BIC above this is not evaluated further (10 short of MIN_DELTA_BIC)
SCORE_RULE_OUT_BIC = 0.0
#: halvings of a candidate's one step that raises chi-square before it is left at its start
STEP_HALVINGS = 5
#: time constants (log-spaced) a lag's refit start is chosen from (Screen.lag_start)
LAG_GRID_POINTS = 10
#: epochs the candidates are tested on (evenly spaced), the fit's own cap (max_fit_samples)
DEFAULT_MAX_SAMPLES = 20000
#: effects that contain each other (adding one when the other is present duplicates terms)
NESTED = {'drift': ('drift2',), 'drift2': ('drift',)}

#: change points of the residual the formula search makes steps and windows of
SEARCH_CHANGE_POINTS = 4
#: search terms listed among the diagnosis' candidates
SEARCH_LISTED = 10

# -- the residual toolkit (measures.py) -------------------------------------------------------
#: evenly sampled: every interval within this share of the median one (a Unix-epoch clock's
#: float64 rounding is 2e-5 of a 100 Hz interval)
EVEN_SAMPLING = 1e-3
#: most epochs x frequencies of one Lomb-Scargle periodogram (more: regridded and FFT-ed)
LS_BUDGET = 4e7
#: a jittered clock: at most this fraction of the intervals outside (1 -+ CLOCK_JITTER) x median
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
#: the same finding on another sensor is the consensus' echo if it removes less than this
#: share of the largest one's mean square
ECHO_RATIO = 0.5
#: fewer epochs than this: no search (the tests' null distributions are asymptotic)
MIN_EPOCHS = 200
#: lag time constants tried per channel
N_TAU = 24
#: half width, in independent frequencies, of the neighbourhood a line is compared with
LINE_NEIGHBOURHOOD = 50

# -- the bases of the formula search (bases.py) -----------------------------------------------
#: numbers of basis functions of the smooth in time the search tries (the grammar's s()
#: takes 3..20; capped by the record)
SMOOTH_K = (4, 8, 12, 20)
#: fewest samples per basis function of a smooth in time
MIN_SAMPLES_PER_K = 25
#: time constants of a lag: LAG_POINTS log-spaced from the first share of the record (at
#: least a sample interval) to the second (:func:`~.measures.lag_grid`)
LAG_FRACTIONS, LAG_POINTS = (0.002, 0.2), 7
#: harmonics of a cyclic smooth
CYCLIC_K = (1, 2, 3)

# -- the formula search (search.py) -----------------------------------------------------------
#: candidates scored exactly after the pre-screen
SCORE_TOP = 40
#: candidates cross-validated after the exact score
CV_TOP = 10
#: pairs are formed from this many of the best validated singles
PAIR_TOP = 5
#: epochs of the pre-screen (evenly spaced)
PRESCREEN_EPOCHS = 2000
#: blocks of the held-out test: folds x blocks per fold
SEARCH_FOLDS, SEARCH_BLOCKS_PER_FOLD = 3, 8
#: held-out shares within this of the best are a tie, decided by fewer parameters
TIE_SHARE = 0.03
#: a sensor is in a term's scope when the driver explains at least this share of what it
#: explains on its best sensor (a disturbance leaks ~5 % into the others through the field)
SCOPE_SHARE = 0.15
#: a term "explains" the excess when it also removes this share of it held out
EXPLAINS_SHARE = 0.8
#: epochs the search works on (evenly spaced; its cost is then independent of the record)
SEARCH_MAX_EPOCHS = 4000
#: most parameters of one candidate term
MAX_TERM_PARAMS = 200
#: the pre-screen of an @alike term is its own joint least squares up to this many
#: parameters (beyond, the sum over the sensors, an upper bound)
ALIKE_EXACT_PARAMS = 60
#: the linear coupling (9 parameters per driver column and sensor) is tried with drivers
#: of at most this many columns: with a smooth, its nine entries describe nothing physical
#: that scale, nonorth and rotation do not, at most of the search's cost
LINEAR_MAX_COLUMNS = 3
#: share of an interval's excess its 5 % largest epochs may hold (more: outliers, not a
#: disturbance confined in time)
SPIKE_SHARE = 0.5
#: a disturbance is localised when its interval is at most this share of the record
MAX_LOCALISED_FRACTION = 0.25

# -- the verdict and the findings fitted (verify.py) ------------------------------------------
#: at most this many terms are fitted to find one the verdict can offer
MAX_VERDICT_TRIES = 3
#: at most this many tokens of the findings are fitted (the rest lose their token)
MAX_FINDING_TRIES = 3
#: a term tying the sensors together (``@alike``, ``field``) is replaced by its variant with
#: each sensor's own parameters when that removes this much more of the held-out excess
SPLIT_SHARE = 0.1

# -- where an excess lies in time (run.py) ----------------------------------------------------
#: the excess "lies within" an interval holding this share of it ...
WHEN_SHARE = 0.8
#: ... when the interval is at most this share of the record (else "throughout the record")
WHEN_SPAN = 0.5
#: an effect of which the field projection leaves less than this share in every direction is
#: one no fit of the magnitude sees (the unknown field direction takes it): not reported as
#: one the record fails to rule out (:func:`.screen.absorbed`)
VISIBLE = 1e-3
