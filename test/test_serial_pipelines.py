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
The live pipelines that must never run beside each other, collected in one file.

``make test`` runs the live tests on two pytest-xdist workers, a file at a time per worker
(scripts/test_lanes.py, ``--dist loadfile``). The three heaviest pipelines are the main job
(`make demo`: four processes at 4 x 100 Hz), the loop demo (its calibrate and diagnose
solves) and the corrector's 4 x 1 kHz burst; two of them side by side starved each other's
streams (the burst's latency bound failed beside the loop, `make demo` lost sets beside it).
Their tests are written in their own files (test_demo.py, test_demo_loop.py,
test_reliability_load.py: read them there) and collected here only
(``conftest.collect_ignore``), so that one worker runs them one after the other.
"""
from test_demo import (test_demo_help_as_the_readme_shows,  # noqa: F401
                       test_make_demo_reaches_the_noise_floor,
                       test_readme_starts_with_make_demo_and_make_test)
from test_demo_loop import (runs, test_judge_by_hand,  # noqa: F401
                            test_loop_closes_for_three_hidden_terms,
                            test_loop_with_a_wrong_model_says_so_and_fails,
                            test_same_term_by_hand)
from test_reliability_load import test_corrector_under_a_10x_burst  # noqa: F401
