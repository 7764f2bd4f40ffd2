"""The executors give the same results in the same order (local in-process, process pool, Ray)."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.augment.executor import map_ordered
from umi_aug.errors import AugmentError


def seeded_task(item: tuple[int, int]) -> tuple[int, bytes]:
    """A deterministic task whose result depends only on its argument (like an episode id → episode)."""
    seed, n = item
    values = np.random.default_rng(seed).normal(size=n)
    return seed, np.cumsum(values).tobytes()


def _items(rng: np.random.Generator, k: int = 9) -> list[tuple[int, int]]:
    return [(int(s), int(n)) for s, n in zip(rng.integers(0, 2**31, k), rng.integers(1, 50, k))]


def test_local_in_process_is_plain_map(rng):
    items = _items(rng)
    assert list(map_ordered(seeded_task, items)) == [seeded_task(i) for i in items]


def test_process_pool_keeps_input_order(rng):
    items = _items(rng)
    got = list(map_ordered(seeded_task, items, workers=2, max_in_flight=3))
    assert got == [seeded_task(i) for i in items]


def test_ray_matches_local(rng):
    ray = pytest.importorskip("ray", reason="Ray is the optional scale-out executor (extra 'ray')")
    import sys

    # Ray's workers do not have pytest's rootdir on sys.path: ship this test module's task by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    items = _items(rng, 6)
    got = list(map_ordered(seeded_task, items, executor="ray", workers=2))
    assert got == [seeded_task(i) for i in items]


@pytest.mark.parametrize("kwargs, match", [({"executor": "dask"}, "executor='dask'"), ({"workers": 0}, "workers=0")])
def test_bad_settings_are_named(kwargs, match):
    with pytest.raises(AugmentError, match=match):
        map_ordered(seeded_task, [], **kwargs)
