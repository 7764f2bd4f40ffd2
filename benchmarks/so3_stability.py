"""SO(3) exp/log numerical stability and speed (numpy float64, torch float64, torch float32, vs scipy).

Run: ``OMP_NUM_THREADS=1 python benchmarks/so3_stability.py``. Reusable pieces for other benchmarks:
``so3_stability_rows()`` (accuracy table, one dict per case × backend), ``so3_timing_rows()`` (speed table) and
``format_table(rows, columns)`` (plain text).

Accuracy metrics, max over random axes (``samples`` per angle):
* ``err_log_exp``: ‖so3_log(so3_exp(v)) − v‖∞, taking the smaller of the two rotation vectors of the same rotation
  (θn and −(2π−θ)n; they only differ in practice at θ ≈ π); for float32 v is the float32-rounded input.
* ``rel_log_exp``: err_log_exp / θ (θ > 0): relative accuracy for tiny angles.
* ``err_exp_log``: ‖so3_exp(so3_log(R)) − R‖∞ with R = so3_exp(v) computed in float64.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Sequence

import numpy as np

CASES: list[tuple[str, float]] = [
    ("0", 0.0),
    ("1e-12", 1e-12),
    ("1e-8", 1e-8),
    ("1e-6", 1e-6),
    ("1e-3", 1e-3),
    ("1", 1.0),
    ("pi/2", math.pi / 2),
    ("pi-1e-3", math.pi - 1e-3),
    ("pi-1e-6", math.pi - 1e-6),
    ("pi-1e-9", math.pi - 1e-9),
    ("pi", math.pi),
]


def _rotvec_err(got: np.ndarray, ref: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(ref, axis=-1, keepdims=True)
    unit = np.where(theta > 0, ref / np.where(theta > 0, theta, 1.0), 0.0)
    alt = -(2 * math.pi - theta) * unit  # same rotation, other representative
    e1 = np.abs(got - ref).max(-1)
    e2 = np.where(theta[..., 0] > 0, np.abs(got - alt).max(-1), np.inf)
    return np.minimum(e1, e2)


def _backends() -> list[tuple[str, Callable, Callable, object]]:
    from umi_aug.geometry import so3_exp, so3_log

    out: list = [("numpy f64", so3_exp, so3_log, np.float64)]
    try:
        import torch

        from umi_aug.geometry import so3_torch as st

        for name, dt in (("torch f64", torch.float64), ("torch f32", torch.float32)):
            out.append(
                (
                    name,
                    lambda v, dt=dt: st.so3_exp(torch.from_numpy(v).to(dt)).double().numpy(),
                    lambda R, dt=dt: st.so3_log(torch.from_numpy(R).to(dt)).double().numpy(),
                    dt,
                )
            )
    except ImportError:  # torch is optional for this benchmark
        pass
    return out


def so3_stability_rows(samples: int = 64, seed: int = 0) -> list[dict]:
    """Max round-trip errors per (angle case, backend). Keys: case, angle_rad, backend, samples,
    err_log_exp, rel_log_exp, err_exp_log, all_finite."""
    from umi_aug.geometry import so3_exp

    rng = np.random.default_rng(seed)
    rows: list[dict] = []
    for case, angle in CASES:
        axes = rng.standard_normal((samples, 3))
        axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
        v64 = axes * angle
        R64 = so3_exp(v64)
        for backend, exp_fn, log_fn, dt in _backends():
            v_in = v64.astype(np.float32).astype(np.float64) if "f32" in backend else v64
            R_in = R64.astype(np.float32).astype(np.float64) if "f32" in backend else R64
            le = log_fn(exp_fn(v_in))
            el = exp_fn(log_fn(R_in))
            err = _rotvec_err(le, v_in)
            theta = np.linalg.norm(v_in, axis=-1)
            rel = float(np.max(err / theta)) if angle > 0 else float("nan")
            rows.append(
                {
                    "case": case,
                    "angle_rad": angle,
                    "backend": backend,
                    "samples": samples,
                    "err_log_exp": float(err.max()),
                    "rel_log_exp": rel,
                    "err_exp_log": float(np.abs(el - R_in).max()),
                    "all_finite": bool(np.isfinite(le).all() and np.isfinite(el).all()),
                }
            )
    return rows


def _best_time(fn: Callable[[], object], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def so3_timing_rows(n: int = 100_000, repeats: int = 5, seed: int = 0) -> list[dict]:
    """Time of one batched call on ``n`` rotations (best of ``repeats``), ours vs scipy in the same process.
    Keys: op, impl, n, us_per_call, ns_per_rotation, ratio_vs_scipy, max_err_vs_scipy."""
    from scipy.spatial.transform import Rotation

    from umi_aug.geometry import so3_exp, so3_log

    rng = np.random.default_rng(seed)
    v = rng.standard_normal((n, 3))
    v *= rng.uniform(0, math.pi, (n, 1)) / np.linalg.norm(v, axis=-1, keepdims=True)
    R = Rotation.from_rotvec(v).as_matrix()
    impls: list[tuple[str, str, Callable[[], np.ndarray]]] = [
        ("exp", "scipy", lambda: Rotation.from_rotvec(v).as_matrix()),
        ("exp", "umi_aug numpy", lambda: so3_exp(v)),
        ("log", "scipy", lambda: Rotation.from_matrix(R).as_rotvec()),
        ("log", "umi_aug numpy", lambda: so3_log(R)),
    ]
    try:
        import torch

        from umi_aug.geometry import so3_torch as st

        vt, Rt = torch.from_numpy(v), torch.from_numpy(R)
        impls.insert(2, ("exp", "umi_aug torch f64", lambda: st.so3_exp(vt).numpy()))
        impls.append(("log", "umi_aug torch f64", lambda: st.so3_log(Rt).numpy()))
    except ImportError:
        pass
    ref = {"exp": Rotation.from_rotvec(v).as_matrix(), "log": Rotation.from_matrix(R).as_rotvec()}
    scipy_t: dict[str, float] = {}
    rows: list[dict] = []
    for op, impl, fn in impls:
        fn()  # warm-up
        t = _best_time(fn, repeats)
        if impl == "scipy":
            scipy_t[op] = t
        rows.append(
            {
                "op": op,
                "impl": impl,
                "n": n,
                "us_per_call": t * 1e6,
                "ns_per_rotation": t * 1e9 / n,
                "ratio_vs_scipy": t / scipy_t[op],
                "max_err_vs_scipy": float(np.abs(fn() - ref[op]).max()),
            }
        )
    return rows


def _fmt(v: object) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        if v == 0.0:
            return "0"
        return f"{v:.3g}" if 1e-3 <= abs(v) < 1e5 else f"{v:.2e}"
    return str(v)


def format_table(rows: Sequence[dict], columns: Sequence[str]) -> str:
    """Plain-text table of ``rows`` restricted to ``columns``."""
    cells = [[_fmt(r[c]) for c in columns] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(x.ljust(w) for x, w in zip(row, widths)) for row in cells]
    return "\n".join(out)


def main() -> None:
    rows = so3_stability_rows()
    print("SO(3) round-trip accuracy (max over random axes)")
    print(format_table(rows, ["case", "backend", "err_log_exp", "rel_log_exp", "err_exp_log", "all_finite"]))
    print()
    trows = so3_timing_rows()
    print(f"SO(3) batched speed, n = {trows[0]['n']} rotations, best of 5 (same process)")
    print(format_table(trows, ["op", "impl", "us_per_call", "ns_per_rotation", "ratio_vs_scipy", "max_err_vs_scipy"]))


if __name__ == "__main__":
    main()
