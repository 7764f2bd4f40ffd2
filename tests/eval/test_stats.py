"""Paired statistics of two policies evaluated on the same configurations (issue #29 part 4): the exact McNemar
test and the paired bootstrap interval of the success-rate difference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from umi_aug.eval.stats import mcnemar_exact_p, paired_bootstrap_interval


def _mcnemar_by_enumeration(only_a: int, only_b: int) -> float:
    """Slow reference: the two-sided exact binomial test by summing every outcome at most as likely as the
    observed one (the definition; equal to twice the smaller tail for p = 1/2, whose pmf is symmetric)."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    pmf = [math.comb(n, i) / 2 ** n for i in range(n + 1)]
    obs = pmf[only_a]
    return min(1.0, sum(p for p in pmf if p <= obs * (1 + 1e-12)))


def test_mcnemar_matches_the_definition_and_scipy(rng):
    from scipy.stats import binomtest

    pairs = [(0, 0), (0, 1), (1, 0), (0, 5), (5, 0), (3, 3), (1, 9), (7, 2), (0, 60), (250, 180), (400, 400)]
    pairs += [tuple(int(v) for v in rng.integers(0, 120, 2)) for _ in range(20)]
    for a, b in pairs:
        p = mcnemar_exact_p(a, b)
        assert np.isfinite(p) and 0.0 < p <= 1.0, (a, b, p)
        assert p == pytest.approx(_mcnemar_by_enumeration(a, b), rel=1e-9, abs=1e-300), (a, b)
        if a + b:
            assert p == pytest.approx(binomtest(a, a + b, 0.5).pvalue, rel=1e-9, abs=1e-300), (a, b)
        assert p == mcnemar_exact_p(b, a)  # symmetric in the two policies
    assert mcnemar_exact_p(0, 5) == pytest.approx(0.0625)  # 2 / 2^5: five discordant pairs all one way
    assert mcnemar_exact_p(0, 0) == 1.0 and mcnemar_exact_p(4, 4) == 1.0
    assert mcnemar_exact_p(0, 2000) == 0.0  # 2^-1999 underflows to 0, never NaN
    with pytest.raises(ValueError, match="only_a=-1"):
        mcnemar_exact_p(-1, 3)


def test_paired_bootstrap_interval(rng):
    n = 400
    x = rng.random(n) < 0.45
    flip = rng.random(n) < 0.2  # the other policy: the same outcome on 80 % of the configurations
    y = np.where(flip, rng.random(n) < 0.3, x)
    lo, hi = paired_bootstrap_interval(x, y, n_boot=4000, seed=1)
    d = x.astype(float) - y.astype(float)
    assert lo <= d.mean() <= hi
    # the width of the paired normal interval (the bootstrap's large-sample limit), within 15 %
    assert (hi - lo) == pytest.approx(2 * 1.959964 * d.std() / math.sqrt(n), rel=0.15)
    # pairing matters: the unpaired interval of two rates this correlated is wider
    unpaired = 2 * 1.959964 * math.sqrt(x.mean() * (1 - x.mean()) / n + y.mean() * (1 - y.mean()) / n)
    assert hi - lo < unpaired
    assert paired_bootstrap_interval(x, y, n_boot=4000, seed=1) == (lo, hi)  # deterministic for a seed
    assert paired_bootstrap_interval(x, x, n_boot=500) == (0.0, 0.0)
    ones, zeros = np.ones(10, bool), np.zeros(10, bool)
    assert paired_bootstrap_interval(ones, zeros, n_boot=100) == (1.0, 1.0)
    assert all(math.isnan(v) for v in paired_bootstrap_interval([], []))
    with pytest.raises(ValueError, match="pair up"):
        paired_bootstrap_interval(ones, zeros[:9])
    with pytest.raises(ValueError, match="n_boot"):
        paired_bootstrap_interval(ones, zeros, n_boot=0)
