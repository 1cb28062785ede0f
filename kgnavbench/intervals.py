"""Intervals for Table I: a cell's mean over seeds with a 95% stratified bootstrap interval, the
difference of two rows with its interval, and a verdict on a comparison the paper draws.

One training run's number is one draw: training is chaotic (another CPU or thread count gives another
model), and a cell averages a finite set of fixed episodes. So a cell is reported as the mean over seeds
of each seed's episode mean, with an interval that resamples both sources of variation:

  * seeds: each replicate draws as many seeds as there are, with replacement;
  * episodes: within each drawn seed, each stratum (a target: targets differ in difficulty, and each
    has a fixed number of episodes) is resampled with replacement, keeping its size, as rliable's
    stratified bootstrap resamples runs within tasks. A resample thus keeps every target's share.

The statistic of a replicate is the mean over its drawn seeds of each drawn seed's resampled episode mean;
the interval is the 2.5th and 97.5th percentile of the replicates (the percentile bootstrap). The point
estimate is the statistic on the data itself, not the mean of the replicates.

Values are whatever the caller gives (Table I gives success as 0 or 100 and SPL terms times 100, so
every number here is in percent). Everything is deterministic given `seed`: an int or a sequence of ints
(numpy's SeedSequence entropy), so a caller can give each row and cell its own stream.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

REPLICATES = 2000  # bootstrap replicates per interval
CONFIDENCE = 0.95
# Elements of the (replicates x episodes) resampling array per block: bounds memory at about 16 MB.
_BLOCK = 1_000_000

HOLDS, REVERSED, CANNOT_TELL = "holds", "reversed", "cannot tell"
# where the paper's effect is there but ours is of another size: d beyond our interval or inside it
HOLDS_SMALLER, HOLDS_LARGER = "holds, smaller than the paper's", "holds, larger than the paper's"
SMALLER = "smaller than the paper's"  # no effect can be told, but the paper's is ruled out
HIGHER, LOWER = "higher", "lower"  # where the paper has no side: ours alone
NO_DIFFERENCE = "no difference beyond"  # + the margin: the interval lies within [-margin, margin]


def no_difference(margin: float) -> str:
    """'no difference beyond 3': the verdict of an interval that lies within [-margin, margin]."""
    return f"{NO_DIFFERENCE} {margin:g}"


def verdicts(margin: float) -> tuple[str, ...]:
    """Every verdict, in the order of precedence `verdict` applies them (and tables count them)."""
    return (
        HOLDS,
        HOLDS_SMALLER,
        HOLDS_LARGER,
        REVERSED,
        HIGHER,
        LOWER,
        no_difference(margin),
        SMALLER,
        CANNOT_TELL,
    )


# A paper difference below this many percentage points has no side: the paper prints one run per row,
# to two decimals, and a difference of a few hundredths of a point claims nothing.
PAPER_TIE = 0.5

# One seed's episodes: (stratum, value) per episode; the stratum is the episode's target.
SeedEpisodes = Sequence[tuple[str, float]]


@dataclass(frozen=True)
class Interval:
    """A point estimate with its percentile interval, in the units of the values (percent in Table I)."""

    estimate: float
    low: float
    high: float


@dataclass(frozen=True, eq=False)  # eq=False: an array has no single truth value
class Bootstrap:
    """The statistic on the data (`estimate`) and on every bootstrap replicate (`replicates`)."""

    estimate: float
    replicates: np.ndarray  # shape (reps,)

    def interval(self, confidence: float = CONFIDENCE) -> Interval:
        """The percentile interval: the middle `confidence` of the replicates."""
        return _percentile_interval(self.estimate, self.replicates, confidence)


def seed_means(per_seed: Sequence[SeedEpisodes]) -> list[float]:
    """Each seed's mean over its episodes (the per-seed numbers a cell averages)."""
    _check(per_seed)
    return [float(np.mean([value for _, value in episodes])) for episodes in per_seed]


def stratified_bootstrap(
    per_seed: Sequence[SeedEpisodes], reps: int = REPLICATES, seed: int | Sequence[int] = 0
) -> Bootstrap:
    """The mean over seeds of per-seed episode means, and its bootstrap replicates: per replicate, seeds
    drawn with replacement, and within each drawn seed its episodes drawn with replacement within each
    stratum (see the module docstring). A seed drawn twice in one replicate gets two independent episode
    resamples. Raises ValueError for no seeds, a seed without episodes, or reps < 1."""
    _check(per_seed)
    episodes = [[(stratum, (value,)) for stratum, value in seed_episodes] for seed_episodes in per_seed]
    return joint_stratified_bootstrap(episodes, reps, seed)[0]


def joint_stratified_bootstrap(
    per_seed: Sequence[Sequence[tuple[str, Sequence[float]]]],
    reps: int = REPLICATES,
    seed: int | Sequence[int] = 0,
) -> list[Bootstrap]:
    """`stratified_bootstrap` of several values per episode at once, (stratum, (value, value, ...)): one
    Bootstrap per value, all from the same resamples. Table I bootstraps a cell's SPL and SR so: drawing
    the resample indices, most of the work, once serves both, and each value's replicates are exactly
    what `stratified_bootstrap` of that value alone gives with the same seed.

    Vectorised: every drawn seed's episode resample is one row of a (draws x episodes) index array, an
    episode's index drawn uniformly from its own stratum's block of the seed's stratum-sorted values."""
    _check(per_seed)
    if reps < 1:
        raise ValueError(f"reps must be at least 1, not {reps}")
    widths = {len(values) for episodes in per_seed for _, values in episodes}
    if len(widths) != 1:
        raise ValueError(f"every episode must have the same number of values, not {sorted(widths)}")
    (width,) = widths
    rng = np.random.default_rng(seed)
    n_seeds = len(per_seed)
    data = [np.array([values for _, values in episodes], dtype=float) for episodes in per_seed]
    estimates = np.mean([d.mean(axis=0) for d in data], axis=0)  # mean over seeds of seeds' means
    drawn = rng.integers(0, n_seeds, size=(reps, n_seeds))  # seeds drawn per replicate
    resampled = np.empty((reps, n_seeds, width))  # each drawn seed's resampled episode means
    for s, episodes in enumerate(per_seed):
        where = np.nonzero(drawn == s)  # (replicate, draw) slots that drew seed s
        if len(where[0]):
            resampled[where] = _stratified_means(
                [stratum for stratum, _ in episodes], data[s], len(where[0]), rng
            )
    replicates = resampled.mean(axis=1)
    return [Bootstrap(float(estimates[v]), replicates[:, v].copy()) for v in range(width)]


def _stratified_means(
    strata: list[str], data: np.ndarray, draws: int, rng: np.random.Generator
) -> np.ndarray:
    """`draws` independent stratified resamples of one seed's episodes (`data`: a row of values per
    episode): the mean of each, shape (draws, values)."""
    order = sorted(range(len(strata)), key=lambda i: strata[i])  # stable: each stratum one block
    values = data[order]
    sorted_strata = [strata[i] for i in order]
    # per position of the sorted values: where its stratum's block starts and how long the block is
    starts = np.empty(len(values), dtype=np.int32)
    sizes = np.empty(len(values), dtype=np.int32)
    begin = 0
    for end in range(1, len(values) + 1):
        if end == len(values) or sorted_strata[end] != sorted_strata[begin]:
            starts[begin:end], sizes[begin:end] = begin, end - begin
            begin = end
    float_sizes = sizes.astype(np.float32)
    columns = [np.ascontiguousarray(values[:, v]) for v in range(values.shape[1])]  # one per value
    means = np.empty((draws, values.shape[1]))
    block = max(1, _BLOCK // len(values))
    for first in range(0, draws, block):
        n = min(block, draws - first)
        # a float32 uniform times the stratum's size, truncated: an offset uniform within the stratum
        uniforms = rng.random((n, len(values)), dtype=np.float32)
        uniforms *= float_sizes
        offsets = uniforms.astype(np.int32)
        np.minimum(offsets, sizes - 1, out=offsets)  # a product rounded up to the size itself
        offsets += starts
        for v, column in enumerate(columns):
            means[first : first + n, v] = column[offsets].mean(axis=1)
    return means


def mean_interval(
    per_seed: Sequence[SeedEpisodes],
    reps: int = REPLICATES,
    seed: int | Sequence[int] = 0,
    confidence: float = CONFIDENCE,
) -> Interval:
    """The mean over seeds of per-seed episode means with its stratified bootstrap percentile interval."""
    return stratified_bootstrap(per_seed, reps, seed).interval(confidence)


def difference(base: Bootstrap, other: Bootstrap, confidence: float = CONFIDENCE) -> Interval:
    """other - base: the difference of the estimates, and the percentile interval of the replicate-by-
    replicate differences. The two bootstraps must come from independent streams (different seeds):
    two rows' runs share nothing, so their resamples must not be paired."""
    if base.replicates.shape != other.replicates.shape:
        raise ValueError(
            f"the two bootstraps have {len(base.replicates)} and {len(other.replicates)} replicates"
        )
    return _percentile_interval(
        other.estimate - base.estimate, other.replicates - base.replicates, confidence
    )


def row_difference(
    base: Sequence[SeedEpisodes],
    other: Sequence[SeedEpisodes],
    reps: int = REPLICATES,
    seed: int | Sequence[int] = 0,
    confidence: float = CONFIDENCE,
) -> Interval:
    """other - base from the episodes of two rows: an independent stratified bootstrap of each (two
    streams spawned from `seed`), differenced replicate by replicate (see `difference`)."""
    base_seed, other_seed = np.random.SeedSequence(seed).spawn(2)
    return difference(
        stratified_bootstrap(base, reps, base_seed), stratified_bootstrap(other, reps, other_seed), confidence
    )


def verdict(paper_difference: float | None, low: float, high: float, margin: float) -> str:
    """What our 95% interval [low, high] of a difference (other - base, in points) says of the paper's
    printed difference d. An end at exactly 0 counts as containing 0. In this order of precedence:

    * the paper has a side (|d| >= PAPER_TIE), and the interval excludes 0
      - on the paper's side: "holds" (it contains d), "holds, smaller than the paper's" (d lies beyond
        it, further from 0), "holds, larger than the paper's" (d lies between 0 and it);
      - on the other side: "reversed";
    * the paper has no side (d is None: a comparison of ours or a cell the paper reports for one row
      only; or |d| < PAPER_TIE), and the interval excludes 0: "higher" or "lower";
    * the interval lies within [-margin, margin]: "no difference beyond MARGIN" (d inside the margin
      agrees with it too: the difference, the paper's included, is small);
    * the paper has a side, the interval contains 0 and excludes d: "smaller than the paper's";
    * else "cannot tell".
    """
    if low > high:
        raise ValueError(f"an interval's low end {low} is above its high end {high}")
    if margin < 0:
        raise ValueError(f"the margin is {margin} points; it must be 0 or more")
    sided = paper_difference is not None and abs(paper_difference) >= PAPER_TIE
    if low > 0 or high < 0:  # the interval excludes 0
        positive = low > 0
        if not sided:
            return HIGHER if positive else LOWER
        if positive != (paper_difference > 0):
            return REVERSED
        if low <= paper_difference <= high:
            return HOLDS
        beyond = abs(paper_difference) > max(abs(low), abs(high))
        return HOLDS_SMALLER if beyond else HOLDS_LARGER
    if -margin <= low and high <= margin:
        return no_difference(margin)
    if sided and not low <= paper_difference <= high:
        return SMALLER
    return CANNOT_TELL


def _percentile_interval(estimate: float, replicates: np.ndarray, confidence: float) -> Interval:
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be between 0 and 1, not {confidence}")
    tail = (100 - 100 * confidence) / 2  # percent of the replicates below the interval (2.5, exactly)
    low, high = np.percentile(replicates, [tail, 100 - tail])
    return Interval(float(estimate), float(low), float(high))


def _check(per_seed: Sequence[SeedEpisodes]) -> None:
    if not per_seed:
        raise ValueError("no seeds to bootstrap")
    empty = [s for s, episodes in enumerate(per_seed) if not episodes]
    if empty:
        raise ValueError(f"seed(s) {empty} have no episodes")


def standard_error(sr: float, episodes: int) -> float:
    """The binomial standard error (points) of an SR in percent measured on `episodes` episodes."""
    p = min(max(sr / 100.0, 0.0), 1.0)
    return 100.0 * math.sqrt(p * (1.0 - p) / max(episodes, 1))


def within_one_standard_error(val_sr: float, val_max: float, episodes: int) -> bool:
    """The one-standard-error reading of the checkpoint rule, as a replay over metrics.csv (the trainer
    keeps the best, the paper's words): a validation SR within one standard error of the best so far
    (val_max, this one included) would select its checkpoint, the latest such one kept."""
    return val_sr >= val_max - standard_error(val_max, episodes)
