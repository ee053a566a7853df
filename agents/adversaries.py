"""Adversarial nominal policies: what a safety filter must survive.

Every adversary acts on the robots' wheels at the limits of the action space
(or beyond, behind a filter, where the nominal is not clipped) and ignores the
task; each is seeded and deterministic.  In ``action_mode="point"`` envs the
wheel accelerations are converted to the equivalent control-point actions.

=========================  =============================================================
name (``--controller``)    behaviour
=========================  =============================================================
``spin_up``                spin in place at full rate (``du = (+a, -a)``), then full
                           throttle forward: the drift ``A_dot u`` outgrows the wheels
``burst``                  stand still, then full throttle forward
``bang_bang``              random ``+-1`` per wheel, held for a few decisions
``chase_nearest``          accelerate at full rate toward the nearest robot
                           (:class:`HostileAgent`)
``chase_target``           every robot chases one other robot chosen at random
``uniform_noise``          uniform random actions in ``[-1, 1]``
=========================  =============================================================

:data:`ADVERSARIES` maps the names to the classes (the safety campaign runs them all).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.model.geometry import k_nearest
from aasoatt_env.model.portable import solve2
from agents.base import register_agent

__all__ = [
    "ADVERSARIES",
    "BangBang",
    "Burst",
    "ChaseTarget",
    "HostileAgent",
    "SpinUp",
    "UniformNoise",
]


def _actions(env: Any, wheel: np.ndarray) -> dict[str, np.ndarray]:
    """Normalised wheel accelerations ``(N, 2)`` as the env's action dict (converted in point mode)."""
    base = env.unwrapped
    act = np.asarray(wheel, dtype=np.float64)
    if base.action_mode == "point":
        kin, team = base.kinematics, base.team
        du = act * team.max_wheel_accel[:, None]
        act = (np.einsum("nij,nj->ni", kin.A, du) + kin.adot_u) / team.max_point_accel[:, None]
    act = act.astype(np.float32)
    idx = base.agent_index
    return {a: act[idx[a]] for a in env.agents}


def _point_toward(env: Any, target: np.ndarray) -> dict[str, np.ndarray]:
    """Full point acceleration toward ``target`` ``(N, 2)``, wheels saturated to ``[-1, 1]``."""
    base = env.unwrapped
    kin, team = base.kinematics, base.team
    d = target - kin.p
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    accel = team.max_point_accel[:, None] * d
    du = solve2(kin.A, accel - kin.adot_u)
    return _actions(env, np.clip(du / team.max_wheel_accel[:, None], -1.0, 1.0))


class _Timed:
    """Counts env steps since ``reset``."""

    def reset(self, env: Any) -> None:
        """Start counting."""
        self.t = 0

    def _tick(self) -> int:
        t = self.t
        self.t += 1
        return t


class SpinUp(_Timed):
    """Spin in place at full wheel acceleration for ``spin_steps`` env steps, then full throttle forward."""

    def __init__(self, spin_steps: int = 200) -> None:
        self.spin_steps = check.integer("spin_steps", spin_steps, lo=0)
        self.t = 0

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """``(+1, -1)`` while spinning, ``(+1, +1)`` after."""
        n = env.unwrapped.team.n
        wheel = np.tile([1.0, -1.0] if self._tick() < self.spin_steps else [1.0, 1.0], (n, 1))
        return _actions(env, wheel)


class Burst(_Timed):
    """Stand still for ``rest_steps`` env steps, then full throttle forward."""

    def __init__(self, rest_steps: int = 100) -> None:
        self.rest_steps = check.integer("rest_steps", rest_steps, lo=0)
        self.t = 0

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """Zero, then ``(+1, +1)``."""
        n = env.unwrapped.team.n
        return _actions(env, np.full((n, 2), 0.0 if self._tick() < self.rest_steps else 1.0))


class BangBang(_Timed):
    """Random ``+-1`` per wheel, held for ``hold`` env steps (seeded)."""

    def __init__(self, seed: int | None = 0, hold: int = 20) -> None:
        self.seed = seed
        self.hold = check.integer("hold", hold, lo=1)
        self.t = 0
        self.rng = np.random.default_rng(seed)  # (as after reset: act() may come first)

    def reset(self, env: Any) -> None:
        """Restart the random sequence."""
        super().reset(env)
        self.rng = np.random.default_rng(self.seed)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """A new sign pattern every ``hold`` steps."""
        if self._tick() % self.hold == 0:
            self.signs = self.rng.choice([-1.0, 1.0], size=(env.unwrapped.team.n, 2))
        return _actions(env, self.signs)


class HostileAgent:
    """Every robot accelerates at full rate toward its nearest neighbour (``chase_nearest``)."""

    def reset(self, env: Any) -> None:
        """Nothing to reset."""

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """Point accelerations of magnitude ``max_point_accel`` toward the nearest robot."""
        p = env.unwrapped.positions
        idx, _, _ = k_nearest(p, 1)
        j = np.where(idx[:, 0] >= 0, idx[:, 0], np.arange(p.shape[0]))
        return _point_toward(env, p[j])


class ChaseTarget:
    """Every robot chases one other robot chosen at random at ``reset`` (seeded)."""

    def __init__(self, seed: int | None = 0) -> None:
        self.seed = seed
        self.target: np.ndarray | None = None  # (picked at reset, or at the first act)

    def reset(self, env: Any) -> None:
        """Pick the targets."""
        n = env.unwrapped.team.n
        rng = np.random.default_rng(self.seed)
        self.target = (np.arange(n) + rng.integers(1, max(n, 2), size=n)) % max(n, 1)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """Full point acceleration toward the target robot."""
        if self.target is None or self.target.shape[0] != env.unwrapped.team.n:
            self.reset(env)
        return _point_toward(env, env.unwrapped.positions[self.target])


class UniformNoise:
    """Uniform random actions in ``[-1, 1]`` per wheel (seeded)."""

    def __init__(self, seed: int | None = 0) -> None:
        self.seed = seed
        self.rng = np.random.default_rng(seed)  # (as after reset: act() may come first)

    def reset(self, env: Any) -> None:
        """Restart the random sequence."""
        self.rng = np.random.default_rng(self.seed)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """One uniform sample per robot."""
        return _actions(env, self.rng.uniform(-1.0, 1.0, size=(env.unwrapped.team.n, 2)))


ADVERSARIES: dict[str, type] = {
    "spin_up": SpinUp,
    "burst": Burst,
    "bang_bang": BangBang,
    "chase_nearest": HostileAgent,
    "chase_target": ChaseTarget,
    "uniform_noise": UniformNoise,
}
"""Adversary registry: name -> class (all registered as ``--controller`` names too)."""

for _name, _cls in ADVERSARIES.items():
    register_agent(_name, _cls)
register_agent("hostile", HostileAgent)
