"""The filter is a function of its inputs and configuration: two fresh processes give the same bits."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

_RUN = """
import hashlib, sys
from aasoatt_env import make_env
from agents import TrackingController
scenario, n, mode, steps = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
env = make_env(scenario, num_robots=n, filter={"mode": mode}, max_steps=10**9)
obs, _ = env.reset(seed=0)
agent, digest, qp_rows = TrackingController(), hashlib.sha256(), 0
for _ in range(steps):
    obs, *_ = env.step(agent.act(obs, env))
    digest.update(env.unwrapped.positions.tobytes())
    qp_rows = max(qp_rows, env.unwrapped.filter_outputs[-1].n_qp_rows)
print(digest.hexdigest(), qp_rows)
"""


def _printed(script: str, *args: str, **env: str) -> list[str]:
    """The words ``script`` prints in a fresh process (``env`` added to this one's environment)."""
    return subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=900,
                          check=True, env={**os.environ, **env}).stdout.split()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["centralized", "decentralized"])
@pytest.mark.parametrize(("scenario", "n"), [("circle_swap", 20), ("random_goals", 120)])
def test_two_processes_step_the_same_positions(scenario, n, mode):
    """2,000 physics steps behind the default filter (the paper's tracking controller): every step's positions
    equal bit for bit in two fresh processes (numba's cache, the heap and the clock differ between them)."""
    runs = [_printed(_RUN, scenario, str(n), mode, "2000") for _ in range(2)]
    assert runs[0] == runs[1]
    assert int(runs[0][1]) > (100 if n == 120 else 10)  # (the QP saw many rows: coupled robots, not closed forms)


_ACROSS = """
import collections, hashlib, sys
from aasoatt_env import make_env
from agents import TrackingController
from agents.adversaries import ADVERSARIES
digest, statuses = hashlib.sha256(), collections.Counter()
for mode in ("centralized", "decentralized"):
    for scenario, n, agent, obstacles, steps in (("random_goals", 20, None, 0, 800), ("circle_swap", 16, None, 0, 800),
                                                 ("random_goals", 16, "spin_up", 4, 300),
                                                 ("random_goals", 16, "chase_nearest", 4, 300)):
        kw = {"random_obstacles": obstacles} if obstacles else {}
        env = make_env(scenario, num_robots=n, filter={"mode": mode}, max_steps=10**9, **kw)
        obs, _ = env.reset(seed=1)
        ctrl = TrackingController() if agent is None else ADVERSARIES[agent]()
        if agent is not None:
            ctrl.reset(env)
        for _ in range(steps):
            obs, *_ = env.step(ctrl.act(obs, env))
            digest.update(env.unwrapped.poses.tobytes())
            statuses[env.unwrapped.filter_outputs[-1].status] += 1
try:  # the torch env (an extra), both dtypes
    import torch
    from aasoatt_env import make_tensor_env
except ImportError:
    torch = None
for dtype in (torch.float64, torch.float32) if torch is not None else ():
    torch.set_num_threads(1)
    env, gen = make_tensor_env("random_goals", 8, 8, dtype=dtype, random_obstacles=2), torch.Generator().manual_seed(0)
    env.reset(seed=1)
    for _ in range(300):
        obs = env.step(torch.rand(8, 8, 2, generator=gen, dtype=dtype) * 2 - 1)[0]
        digest.update(obs.numpy().tobytes())
print(digest.hexdigest(), *sorted(statuses.items()))
"""


def _other_cpus() -> dict[str, dict[str, str]]:
    """Environment variables under which this machine runs the kernels another x86-64 CPU would (AVX2 + FMA)."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    if platform.machine() not in ("x86_64", "AMD64") or not (__cpu_features__["AVX2"] and __cpu_features__["FMA3"]):
        return {}
    avx512 = [f for f in __cpu_dispatch__ if "512" in f or f == "X86_V4"]
    others = {"AVX2 machine": {"NPY_DISABLE_CPU_FEATURES": " ".join(avx512), "OPENBLAS_CORETYPE": "Haswell",
                               "NUMBA_CPU_NAME": "haswell", "ATEN_CPU_CAPABILITY": "avx2"}}
    if __cpu_features__.get("AVX512F"):
        others["Intel AVX-512 BLAS"] = {"OPENBLAS_CORETYPE": "SkylakeX"}
    return others


@pytest.mark.slow
def test_the_same_bits_on_other_x86_cpus():
    """Rollouts behind the default filter (both modes; the tracking law, and adversaries among obstacles, where the
    backup layer and relaxed QPs answer) and of the torch env give the same bits when numpy, OpenBLAS, numba and
    torch run the kernels they would pick on another AVX2 + FMA CPU (numpy's AVX-512 loops off; OpenBLAS's Haswell or
    Intel AVX-512 kernels; numba compiling for Haswell; torch's AVX2 kernels).  :mod:`aasoatt_env.model.portable`
    says what this needs."""
    others = _other_cpus()
    if not others:
        pytest.skip("needs an x86-64 CPU with AVX2 and FMA")

    here = _printed(_ACROSS)
    assert any(s.startswith("('backup'") for s in here) and any(s.startswith("('relaxed'") for s in here), here
    for name, extra in others.items():
        assert _printed(_ACROSS, **extra) == here, name


_EQUALITY = """
import hashlib, numpy as np, scipy.sparse as sp
from aasoatt_env.safety.solvers.active_set import _equality_point
rng = np.random.default_rng(0)
M = rng.standard_normal((400, 300))
W = np.zeros(400, dtype=bool)
W[:250] = True  # a working set of 250 rows: OpenBLAS's syrk and potrf thread from 64
gt, b = rng.standard_normal(300), rng.standard_normal(400)
Ms = sp.random(400, 300, density=0.05, random_state=1, format="csr")  # sparse rows, a Schur complement factored dense
for rows, dense, w in ((M, True, W), (Ms, False, W & (np.arange(400) < 180))):
    y, lam, r = _equality_point(rows, dense, gt, b, w)
    print(hashlib.sha256(y.tobytes() + lam.tobytes() + r.tobytes()).hexdigest())
"""


def test_the_active_sets_equality_point_does_not_follow_the_blas_thread_count():
    """The numpy active set's Schur complement and its factor (the path of a QP beyond the compiled kernel's dense
    size, e.g. 150 robots in a 19.5 m arena, and of kernel="numpy"): the same bits with 1, 2 and 4 OpenBLAS
    threads (LAPACK's potrf and numpy's A @ A.T (syrk) split their sums by the thread count)."""
    runs = {t: _printed(_EQUALITY, OPENBLAS_NUM_THREADS=t, OMP_NUM_THREADS=t) for t in ("1", "2", "4")}
    assert runs["1"] == runs["2"] == runs["4"]
