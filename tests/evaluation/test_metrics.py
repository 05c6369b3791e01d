"""Convergence and recovery counting, checked on hand-made error sequences."""

from __future__ import annotations

import numpy as np

from pipeline.evaluation.metrics import first_settled, replay_metrics


def test_first_settled_needs_a_hold_or_the_end():
    e = np.array([5, 0.1, 0.2, 5, 0.1, 0.1, 0.1, 0.1, 5, 0.1, 0.1])
    assert first_settled(e, 0, 0.5, hold=3) == 4  # 1..2 is too short, 4..7 holds
    assert first_settled(e, 8, 0.5, hold=3) == 9  # the last two steps hold to the end
    assert first_settled(e, 0, 0.01, hold=3) is None
    assert first_settled(np.array([]), 0, 0.5, 3) is None


def test_metrics_skip_the_kidnapped_intervals():
    e = np.r_[np.full(5, 9.0), np.full(20, 0.1), np.full(4, 7.0), np.full(21, 0.2)]
    m = replay_metrics(e, [25], np.full(50, 500), np.full(50, 2.0), np.ones(50, bool), hold=10)
    assert m["converged_step"] == 5 and m["recovery_steps"] == [4] and m["recovered"] == 1
    assert m["error_mean_m"] == np.float64(np.r_[np.full(20, 0.1), np.full(21, 0.2)].mean()).round(4)
    never = replay_metrics(np.full(30, 3.0), [10], np.full(30, 10), np.ones(30), np.zeros(30, bool))
    assert never["converged_step"] is None and never["recovery_steps"] == [None] and never["error_median_m"] is None
    assert never["update_ms_mean"] is None


def test_final_error_of_each_kidnapping_is_the_median_before_the_next():
    from pipeline.evaluation.metrics import replay_metrics

    err = np.r_[np.zeros(10), np.full(10, 5.0), np.full(5, 1.0), np.full(5, 0.2), np.full(10, 3.0)]
    m = replay_metrics(err, [10, 30], np.ones(40), np.zeros(40), np.ones(40, bool), threshold_m=0.5, hold=5)
    assert m["recovery_final_error_m"] == [0.2, 3.0]  # the last 5 steps before step 30, then before the end


def test_final_error_of_a_late_kidnapping_counts_only_steps_after_its_recovery():
    from pipeline.evaluation.metrics import replay_metrics

    # Kidnapped 6 steps before the end, recovered 4 steps later: the search (9 m) is not where it ended up.
    err = np.r_[np.zeros(20), np.full(4, 9.0), np.full(2, 0.05)]
    m = replay_metrics(err, [20], np.ones(26), np.zeros(26), np.ones(26, bool), threshold_m=0.5, hold=10)
    assert m["recovery_steps"] == [4]
    assert m["recovery_final_error_m"] == [0.05]


def test_a_filter_that_converges_then_walks_away_has_lost_track():
    # Converged at step 0, error grows linearly from step 30 (a filter drifting off), never comes back.
    err = np.r_[np.full(30, 0.1), 0.1 + 0.05 * np.arange(1, 71)]
    m = replay_metrics(err, [], np.ones(100), np.zeros(100), np.ones(100, bool), threshold_m=0.5, hold=10)
    first_bad = int(np.argmax(err >= 0.5))  # 0.1 + 0.05 * 8 = 0.5 at index 37
    assert m["converged_step"] == 0 and m["lost_track_steps"] == [first_bad] == [37]
    assert m["regained_steps"] == [None] and m["held"] is False
    assert m["within_threshold_share"] == round(first_bad / 100, 4)
    assert m["error_median_all_m"] == round(float(np.median(err)), 4)
    assert m["error_median_m"] == m["error_median_all_m"]  # converged at 0: the same steps


def test_lost_then_regained_and_short_excursions():
    # 20 good, 3 bad (too short to count), 20 good, 15 bad (lost), 12 good (regained), then lost to the end (5).
    err = np.r_[np.full(20, 0.1), np.full(3, 2.0), np.full(20, 0.1), np.full(15, 3.0), np.full(12, 0.1),
                np.full(5, 4.0)]
    m = replay_metrics(err, [], np.ones(75), np.zeros(75), np.ones(75, bool), threshold_m=0.5, hold=10)
    assert m["lost_track_steps"] == [43, 70] and m["regained_steps"] == [58, None] and not m["held"]
    held = replay_metrics(err[:43], [], np.ones(43), np.zeros(43), np.ones(43, bool), threshold_m=0.5, hold=10)
    assert held["lost_track_steps"] == [] and held["held"] is True


def test_a_kidnapping_is_not_losing_track():
    # Kidnapped at 30 and recovered at 40: the search is the kidnapping's, not a divergence. A divergence
    # after the recovery is one.
    err = np.r_[np.full(30, 0.1), np.full(10, 6.0), np.full(20, 0.1), np.full(12, 1.0)]
    m = replay_metrics(err, [30], np.ones(72), np.zeros(72), np.ones(72, bool), threshold_m=0.5, hold=10)
    assert m["recovery_steps"] == [10] and m["lost_track_steps"] == [60] and m["regained_steps"] == [None]
    # Tracked steps: 0..29 and 40..71 (62), of which 50 within the threshold.
    assert m["within_threshold_share"] == round(50 / 62, 4)
    never = replay_metrics(np.full(30, 3.0), [], np.ones(30), np.zeros(30), np.ones(30, bool))
    assert never["lost_track_steps"] == [] and never["held"] is False and never["within_threshold_share"] is None
