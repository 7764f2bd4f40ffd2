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


def slow_build(key: str) -> str:
    """A build whose result is its key, written where the items can check it ran first."""
    import os
    import time

    folder = os.environ["UMI_AUG_TEST_BUILD_DIR"]
    time.sleep(0.05 * (hash(key) % 3))  # builds finish out of order
    with open(os.path.join(folder, key), "w") as fh:
        fh.write(key)
    return key.upper()


def needs_build(item: tuple[str, int]) -> tuple[str, int, bool]:
    """An item that reports whether its key's build had finished when it ran."""
    import os

    key, k = item
    return key, k, os.path.exists(os.path.join(os.environ["UMI_AUG_TEST_BUILD_DIR"], key))


def _keyed_items() -> list[tuple[str, int]]:
    return [(key, k) for key in ("a", "b", "c", "d") for k in range(3)] + [("a", 9)]


@pytest.mark.parametrize("executor, workers", [("local", 1), ("local", 2), ("ray", 2)])
def test_builds_run_once_before_the_items_that_need_them(tmp_path, monkeypatch, executor, workers):
    if executor == "ray":
        ray = pytest.importorskip("ray", reason="Ray is the optional scale-out executor (extra 'ray')")
        import sys

        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    monkeypatch.setenv("UMI_AUG_TEST_BUILD_DIR", str(tmp_path))  # spawned / Ray workers inherit it
    items = _keyed_items()
    built: list[tuple[str, str]] = []
    got = list(map_ordered(needs_build, items, executor=executor, workers=workers, needs=lambda it: it[0],
                           build=slow_build, on_built=lambda k, v: built.append((k, v)), max_in_flight=2))
    assert got == [(key, k, True) for key, k in items]  # input order, every item after its build
    assert sorted(built) == [(k, k.upper()) for k in "abcd"]  # one build per key, its value reported here


def failing_build(key: str) -> str:
    if key == "c":
        raise ValueError("scene c: no points")
    return key


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failed_build_is_raised_after_every_earlier_result(tmp_path, monkeypatch, workers):
    monkeypatch.setenv("UMI_AUG_TEST_BUILD_DIR", str(tmp_path))
    items = _keyed_items()
    it = map_ordered(lambda_free_identity, items, workers=workers, needs=lambda it: it[0], build=failing_build)
    got = []
    with pytest.raises(ValueError, match="scene c: no points"):
        for r in it:
            got.append(r)
    assert got == items[:6]  # a and b (the last item, a again, comes after c: never reached)


def lambda_free_identity(item):
    return item


def test_items_needing_nothing_run_without_builds(rng):
    items = _items(rng)
    got = list(map_ordered(seeded_task, items, workers=2, needs=lambda it: None, build=failing_build))
    assert got == [seeded_task(i) for i in items]


def test_build_without_needs_is_refused():
    with pytest.raises(AugmentError, match="`build` and `needs` go together"):
        map_ordered(seeded_task, [], build=failing_build)


def build_meeting_the_other(key: str) -> str:
    """A build that only finishes once the other key's build has started: two builds at once, or a timeout."""
    import os
    import time

    folder = os.environ["UMI_AUG_TEST_BUILD_DIR"]
    open(os.path.join(folder, f"started_{key}"), "w").close()
    other = os.path.join(folder, f"started_{'b' if key == 'a' else 'a'}")
    deadline = time.monotonic() + 120.0
    while not os.path.exists(other):
        if time.monotonic() > deadline:
            raise TimeoutError(f"build {key}: the other scene's build never started alongside it")
        time.sleep(0.01)
    return key


def test_two_workers_build_two_scenes_at_once(tmp_path, monkeypatch):
    """The items of scene a come first, yet scene b builds beside scene a (not after it, as when the episode
    tasks built their scene on first use and the second worker waited on the first one's lock)."""
    monkeypatch.setenv("UMI_AUG_TEST_BUILD_DIR", str(tmp_path))
    items = [("a", k) for k in range(4)] + [("b", k) for k in range(4)]
    got = list(map_ordered(lambda_free_identity, items, workers=2, needs=lambda it: it[0],
                           build=build_meeting_the_other))
    assert got == items


def test_items_are_consumed_lazily_when_nothing_is_built(rng):
    """Without builds the items are pulled as they are submitted (a generator's memory stays bounded)."""
    pulled = []

    def items():
        for it in _items(rng, 20):
            pulled.append(it)
            yield it

    it = map_ordered(seeded_task, items(), workers=2, max_in_flight=2)
    first = next(it)
    assert first == seeded_task(pulled[0]) and len(pulled) <= 4  # 2 in flight + the head, not all 20
    assert len(list(it)) == 19
