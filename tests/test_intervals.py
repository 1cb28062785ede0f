"""The intervals of Table I's cells and comparisons, on numbers small enough to work out by hand."""

from __future__ import annotations

import time

import numpy as np
import pytest

from kgnavbench.intervals import (
    CANNOT_TELL,
    HIGHER,
    HOLDS,
    HOLDS_LARGER,
    HOLDS_SMALLER,
    LOWER,
    REVERSED,
    SMALLER,
    Bootstrap,
    Interval,
    difference,
    joint_stratified_bootstrap,
    mean_interval,
    row_difference,
    seed_means,
    stratified_bootstrap,
    verdict,
)


def constant(value: float, targets: int = 3, episodes: int = 4) -> list[tuple[str, float]]:
    """One seed whose every episode has the same value."""
    return [(f"t{t}", value) for t in range(targets) for _ in range(episodes)]


def test_one_seed_with_equal_episodes_has_a_zero_width_interval_at_that_value():
    assert mean_interval([constant(100.0)]) == Interval(100.0, 100.0, 100.0)
    assert mean_interval([constant(37.5)]) == Interval(37.5, 37.5, 37.5)


def test_the_estimate_is_the_mean_of_the_seeds_means_not_of_all_episodes():
    # seed 0: 1 of 4 episodes succeeds (25); seed 1: 2 of 2 (100). Pooled it would be 3 / 6 = 50.
    per_seed = [[("a", 100.0), ("a", 0.0), ("b", 0.0), ("b", 0.0)], [("a", 100.0), ("b", 100.0)]]
    assert seed_means(per_seed) == [25.0, 100.0]
    assert stratified_bootstrap(per_seed).estimate == 62.5


def test_episodes_are_resampled_within_targets():
    # target a always succeeds, target b never: a stratified resample keeps 5 episodes of each, so
    # every replicate is exactly 50 (resampling across targets would give anything from 0 to 100)
    per_seed = [[("a", 100.0)] * 5 + [("b", 0.0)] * 5]
    boot = stratified_bootstrap(per_seed, reps=500)
    assert set(boot.replicates) == {50.0}
    assert boot.interval() == Interval(50.0, 50.0, 50.0)
    # within a target the episodes are resampled: one target with [0, 100] gives 0, 50 or 100
    boot = stratified_bootstrap([[("a", 0.0), ("a", 100.0)]], reps=2000)
    assert set(boot.replicates) == {0.0, 50.0, 100.0}
    assert boot.interval() == Interval(50.0, 0.0, 100.0)


def test_seeds_are_resampled_with_replacement():
    # seed 0 scores 0 on every episode, seed 1 scores 100: episode resampling changes nothing, so a
    # replicate is 0 (seed 0 drawn twice, p = 1/4), 50 (one of each, 1/2) or 100 (seed 1 twice, 1/4).
    # Both ends have far more than 2.5% of the replicates: the interval is [0, 100] around 50.
    boot = stratified_bootstrap([constant(0.0), constant(100.0)], reps=2000, seed=3)
    values, counts = np.unique(boot.replicates, return_counts=True)
    assert list(values) == [0.0, 50.0, 100.0]
    assert counts / 2000 == pytest.approx([0.25, 0.5, 0.25], abs=0.05)
    assert boot.interval() == Interval(50.0, 0.0, 100.0)


def test_the_interval_is_the_percentile_interval_of_the_replicates():
    # 1001 replicates 0..1000: numpy's linear percentiles 2.5 and 97.5 fall on 25 and 975
    assert Bootstrap(500.0, np.arange(1001.0)).interval() == Interval(500.0, 25.0, 975.0)
    assert Bootstrap(500.0, np.arange(1001.0)).interval(0.5) == Interval(500.0, 250.0, 750.0)


def test_the_bootstrap_is_deterministic_given_its_seed():
    rng = np.random.default_rng(7)
    per_seed = [[(f"t{i % 10}", float(rng.random() < 0.3)) for i in range(200)] for _ in range(3)]
    a = stratified_bootstrap(per_seed, reps=300, seed=11)
    b = stratified_bootstrap(per_seed, reps=300, seed=11)
    c = stratified_bootstrap(per_seed, reps=300, seed=12)
    assert np.array_equal(a.replicates, b.replicates) and a.interval() == b.interval()
    assert not np.array_equal(a.replicates, c.replicates)
    # a sequence of ints is a seed too (Table I gives every row, cell and metric its own)
    d = stratified_bootstrap(per_seed, reps=300, seed=(5, 1, 0))
    assert np.array_equal(d.replicates, stratified_bootstrap(per_seed, reps=300, seed=(5, 1, 0)).replicates)
    # the interval of a noisy cell holds its estimate and is narrower than the values' range
    low, high = a.interval().low, a.interval().high
    assert 0 < low < a.estimate < high < 1


def test_a_joint_bootstrap_resamples_several_values_together():
    # (SPL, SR) per episode: each value's replicates are those of its own bootstrap with the same seed
    rng = np.random.default_rng(1)
    per_seed = [
        [(f"t{i % 7}", (100.0 * rng.random(), 100.0 * (rng.random() < 0.5))) for i in range(50)]
        for _ in range(3)
    ]
    spl, sr = joint_stratified_bootstrap(per_seed, reps=200, seed=4)
    for m, joint in enumerate((spl, sr)):
        alone = stratified_bootstrap([[(t, v[m]) for t, v in seed] for seed in per_seed], reps=200, seed=4)
        assert joint.estimate == pytest.approx(alone.estimate) and np.allclose(
            joint.replicates, alone.replicates
        )
    with pytest.raises(ValueError, match="same number of values"):
        joint_stratified_bootstrap([[("a", (1.0, 2.0)), ("a", (1.0,))]])


def test_three_seeds_of_3000_episodes_with_2000_replicates_are_quick():
    rng = np.random.default_rng(0)
    per_seed = [[(f"t{i % 150}", 100.0 * (rng.random() < 0.4)) for i in range(3000)] for _ in range(3)]
    start = time.perf_counter()
    stratified_bootstrap(per_seed, reps=2000)
    # about 0.3 s on the 2-core development machine under load; a loop over replicates takes minutes
    assert time.perf_counter() - start < 5


def test_bad_input():
    with pytest.raises(ValueError, match="no seeds"):
        stratified_bootstrap([])
    with pytest.raises(ValueError, match=r"seed\(s\) \[1\] have no episodes"):
        stratified_bootstrap([constant(1.0), []])
    with pytest.raises(ValueError, match="reps"):
        stratified_bootstrap([constant(1.0)], reps=0)
    with pytest.raises(ValueError, match="replicates"):
        difference(Bootstrap(0.0, np.zeros(3)), Bootstrap(0.0, np.zeros(4)))
    with pytest.raises(ValueError, match="confidence"):
        Bootstrap(0.0, np.zeros(3)).interval(1.5)


def test_a_difference_is_other_minus_base_replicate_by_replicate():
    base = stratified_bootstrap([constant(20.0)], reps=100, seed=1)
    other = stratified_bootstrap([constant(70.0)], reps=100, seed=2)
    assert difference(base, other) == Interval(50.0, 50.0, 50.0)
    assert difference(other, base) == Interval(-50.0, -50.0, -50.0)
    # replicate by replicate: replicates [0, 1, ..., 1000] less a constant 100
    assert difference(Bootstrap(100.0, np.full(1001, 100.0)), Bootstrap(600.0, np.arange(1001.0))) == (
        Interval(500.0, -75.0, 875.0)
    )


def test_two_rows_are_bootstrapped_independently():
    # the same two seeds (0 and 100) for both rows: each row's replicate is 0, 50 or 100 (1/4, 1/2,
    # 1/4). Paired resamples would make every difference 0; independent ones give -100 with
    # p = 1/16 > 2.5%, and +100 likewise, so the interval is [-100, 100] around 0.
    per_seed = [constant(0.0), constant(100.0)]
    interval = row_difference(per_seed, per_seed, reps=2000, seed=0)
    assert interval == Interval(0.0, -100.0, 100.0)
    assert row_difference(per_seed, per_seed, reps=2000, seed=0) == interval  # deterministic


def test_verdicts_in_their_order_of_precedence():
    """Each verdict on hand-made intervals [low, high] against the paper's difference d, margin 3."""
    m = 3.0
    # the paper has a side, the interval excludes 0 on it: holds (contains d) ...
    assert verdict(4.3, 1.0, 6.0, m) == HOLDS == "holds"
    assert verdict(-0.6, -5.0, -0.5, m) == HOLDS
    assert verdict(4.3, 4.3, 6.0, m) == HOLDS  # d at an end is inside
    # ... smaller than the paper's (d beyond the interval, further from 0) ...
    assert verdict(8.53, 1.0, 6.0, m) == HOLDS_SMALLER == "holds, smaller than the paper's"
    assert verdict(-8.0, -6.0, -1.0, m) == HOLDS_SMALLER
    # ... larger than the paper's (d between 0 and the interval)
    assert verdict(2.3, 3.0, 9.0, m) == HOLDS_LARGER == "holds, larger than the paper's"
    assert verdict(-0.6, -9.0, -1.0, m) == HOLDS_LARGER
    # reversed: it excludes 0 on the other side, whatever its size (inside the margin too)
    assert verdict(4.3, -6.0, -1.0, m) == REVERSED == "reversed"
    assert verdict(-0.6, 0.5, 2.0, m) == REVERSED
    # the paper has no side (no difference, or under half a point: -0.03 claims nothing): ours alone,
    # before the margin
    assert verdict(None, 1.0, 6.0, m) == HIGHER == "higher"
    assert verdict(0.0, -6.0, -1.0, m) == LOWER == "lower"
    assert verdict(-0.03, -2.5, -0.5, m) == LOWER
    assert verdict(0.49, 0.5, 2.0, m) == HIGHER
    # no difference beyond the margin: the interval contains 0 and lies within [-3, 3]
    assert verdict(8.53, -2.9, 2.9, m) == "no difference beyond 3"
    assert verdict(None, -3.0, 3.0, m) == "no difference beyond 3"  # the margin's ends are inside
    assert verdict(2.3, 0.0, 3.0, m) == "no difference beyond 3"  # an end at 0 contains 0
    assert verdict(0.0, 0.0, 0.0, m) == "no difference beyond 3"
    assert verdict(1.0, -1.0, 1.0, 1.5) == "no difference beyond 1.5"
    # smaller than the paper's: the paper has a side, the interval contains 0, excludes d, is wider
    assert verdict(8.53, -2.9, 4.4, m) == SMALLER == "smaller than the paper's"
    assert verdict(-8.0, -4.0, 0.0, m) == SMALLER
    assert verdict(2.3, -3.5, 2.0, m) == SMALLER
    # cannot tell: it contains 0 and d (or the paper has no side), and reaches beyond the margin
    assert verdict(4.3, -1.0, 6.0, m) == CANNOT_TELL == "cannot tell"
    assert verdict(4.3, 0.0, 6.0, m) == CANNOT_TELL
    assert verdict(-4.3, -6.0, 0.0, m) == CANNOT_TELL
    assert verdict(None, -1.0, 6.0, m) == CANNOT_TELL
    assert verdict(0.2, -3.5, 1.0, m) == CANNOT_TELL  # no side: never smaller than the paper's
    # a margin of 0: only an interval of exactly 0 reads no difference
    assert verdict(None, -0.1, 0.1, 0.0) == CANNOT_TELL
    with pytest.raises(ValueError, match="low end"):
        verdict(1.0, 2.0, 1.0, m)
    with pytest.raises(ValueError, match="margin"):
        verdict(1.0, 0.0, 1.0, -1.0)
