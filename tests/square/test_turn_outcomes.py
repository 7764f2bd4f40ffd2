"""The counting helpers of ``benchmarks/square_turn_outcomes.py`` (issue #29 §4m): turn bins and demos near a yaw,
against plain loops on fresh random inputs, wrap-around and bin edges included."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_SPEC = importlib.util.spec_from_file_location(
    "square_turn_outcomes", Path(__file__).resolve().parents[2] / "benchmarks" / "square_turn_outcomes.py")
tto = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(tto)


def test_turn_bins_match_a_loop_and_keep_the_last_bin_open(rng):
    edges = tto.TURN_EDGES_DEG
    turns = np.concatenate([rng.uniform(0.0, 95.0, 500), np.asarray(edges), [0.0, 90.0, 90.2, 120.0]])
    want = []
    for t in turns:
        k = len(edges) - 2  # the last bin takes everything from edges[-2] on
        for i in range(len(edges) - 2):
            if edges[i] <= t < edges[i + 1]:
                k = i
                break
        want.append(k)
    assert tto.turn_bins(turns).tolist() == want
    for bad in ([-0.1], [float("nan")], [float("inf")]):
        with pytest.raises(ValueError, match="finite and >= 0"):
            tto.turn_bins(np.asarray(bad))


def test_demos_near_yaw_counts_over_a_full_turn(rng):
    yaw = np.concatenate([rng.uniform(-180.0, 180.0, 200), [179.0, -179.0, 180.0]])
    demo = np.concatenate([rng.uniform(-180.0, 180.0, 50), [-178.0, 178.0]])
    got = tto.demos_near_yaw(yaw, demo, 15.0)
    for y, n in zip(yaw, got):
        assert n == sum(min(abs(y - d), 360.0 - abs(y - d)) <= 15.0 for d in demo)
    assert tto.demos_near_yaw(np.array([179.0]), np.array([-179.0]), 2.0).tolist() == [1]  # across ±180°
    assert tto.demos_near_yaw(np.array([90.0]), np.array([-90.0]), 15.0).tolist() == [0]  # the handle's side
