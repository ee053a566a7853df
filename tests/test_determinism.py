"""Bit-reproducibility of filtered rollouts (docs/design.md, "Which solver answers: a table, not a clock").

Two fresh runs with the same seed in the same process must give identical
positions, bit for bit.  With the exact solvers that only use numpy/scipy
(``ldp``) or a scalar C solver (``daqp``) they do.  With the default
``proxsuite`` they do too at this size: problems of up to 500 variables take the
exact path first (warm active set, then ``EXACT_ROUTE``, see ``SolverPolicy``).  Larger
coupled groups still reach proxsuite, whose AVX-512/AVX2 builds return last-bit
different answers to the *same* QP depending on where its work buffers land on
the heap; the closed loop amplifies those 1e-16 differences.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from aasoatt_env.api.factory import make_env
from aasoatt_env.safety import available_solvers
from agents import TrackingController

STEPS = 500


def _positions(solver: str, steps: int = STEPS, n: int = 20, seed: int = 0) -> np.ndarray:
    env = make_env("random_goals", num_robots=n, filter={"solver": solver})
    obs, _ = env.reset(seed=seed)
    ctrl = TrackingController(saturate=False)
    ctrl.reset(env)
    out = []
    for _ in range(steps):
        obs, *_ = env.step(ctrl.act(obs, env))
        out.append(env.unwrapped.positions)
    env.close()
    return np.array(out)


@pytest.mark.parametrize("solver", ["ldp", pytest.param("daqp", marks=pytest.mark.skipif(
    "daqp" not in available_solvers(), reason="DAQP not installed"))])
def test_two_fresh_filtered_runs_are_bit_identical(solver: str) -> None:
    a, b = _positions(solver), _positions(solver)
    assert np.array_equal(a, b), f"first difference at step {np.flatnonzero(np.any(a != b, axis=(1, 2)))[0]}"


def test_two_fresh_filtered_runs_are_bit_identical_default_solver() -> None:
    a, b = _positions("proxsuite"), _positions("proxsuite")
    assert np.array_equal(a, b), f"first difference at step {np.flatnonzero(np.any(a != b, axis=(1, 2)))[0]}"


def test_bare_runs_are_bit_identical() -> None:
    def run() -> np.ndarray:
        env = make_env("random_goals", num_robots=20)
        obs, _ = env.reset(seed=3)
        ctrl = TrackingController(saturate=True)
        ctrl.reset(env)
        out = []
        for _ in range(STEPS):
            obs, *_ = env.step(ctrl.act(obs, env))
            out.append(env.unwrapped.positions)
        return np.array(out)

    assert np.array_equal(run(), run())


@pytest.mark.slow
def test_filtered_runs_are_bit_identical_across_processes_and_hash_seeds(tmp_path) -> None:
    tests = os.path.dirname(__file__)
    code = (f"import sys, numpy as np; sys.path.insert(0, {tests!r}); from test_determinism import _positions; "
            "np.save(sys.argv[1], _positions('ldp', 300))")
    files = []
    for hash_seed in ("1", "2"):
        path = tmp_path / f"p{hash_seed}.npy"
        subprocess.run([sys.executable, "-c", code, str(path)], check=True,
                       env={**os.environ, "PYTHONHASHSEED": hash_seed})
        files.append(np.load(path))
    assert np.array_equal(files[0], files[1])
    assert np.array_equal(files[0], _positions("ldp", 300))
