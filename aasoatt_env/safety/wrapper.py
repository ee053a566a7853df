"""``AASOATTFilter``: the CBF-QP safety filter as a drop-in PettingZoo wrapper.

Any policy's actions become the *nominal*; at every physics step (also inside
a ``decision_interval``) the wrapper's :class:`FilterHook` projects the nominal
wheel accelerations through :class:`~aasoatt_env.safety.core.SafetyFilter`
before the env integrates them.  Behind the filter, actions outside
``[-1, 1]`` are accepted as the (unclipped) nominal: the QP keeps the input
bounds hard, so the applied ``du`` always satisfies them.

``infos[agent]["filter"]`` after every step, aggregated over the physics steps
of the env step:

==================  =====================================================
key                 meaning
==================  =====================================================
``intervened``      the filter changed this robot's nominal at some step
``avoiding``        some barrier row of this robot was active (eta > 0)
``triggered``       the deadlock strategy acted on this robot
``correction``      largest ``|du_safe - du_nominal|`` [rad/s^2]
``status``          worst QP status of the team: solved < relaxed < failed
``slack``           largest row relaxation (0 unless ``relaxed``)
``solve_time``      total filter wall time [s] of the env step
``iterations``      total solver iterations
``n_rows``          barrier rows at the last physics step
``n_qp_rows``       of those, rows the QP solver saw (0: closed form sufficed)
==================  =====================================================

The centralised Gymnasium view takes the same options:
``AASOATTGymEnv(scenario, safety_filter={"barrier": "aasoatt", ...})``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.core import FilterResult, SafetyFilter

__all__ = ["AASOATTFilter", "FilterHook"]

_SEVERITY = {"solved": 0, "relaxed": 1, "failed": 2}


class FilterHook:
    """Per-physics-step control filter installed into the env (see module docstring)."""

    def __init__(self, base_env: Any, config: FilterConfig) -> None:
        self.base = base_env
        self.config = config
        self.filter: SafetyFilter | None = None
        self.last_result: FilterResult | None = None
        self._clear()

    def _clear(self) -> None:
        n = len(self.base.possible_agents)
        self.intervened = np.zeros(n, dtype=bool)
        self.avoiding = np.zeros(n, dtype=bool)
        self.triggered = np.zeros(n, dtype=bool)
        self.correction = np.zeros(n)
        self.status = "solved"
        self.message = ""
        self.slack = 0.0
        self.solve_time = 0.0
        self.iterations = 0
        self.applied = np.zeros((n, 2))

    def reset(self) -> None:
        """Build the filter for the episode's team and forget warm starts."""
        team = self.base.team
        if self.filter is None or self.filter.team is not team:
            self.filter = SafetyFilter(team, self.config)
        self.filter.reset()
        self.last_result = None
        self._clear()

    def begin_step(self) -> None:
        """Start aggregating a new env step."""
        self._clear()

    def __call__(self, sim: Any, nominal_du: np.ndarray) -> np.ndarray:
        """Filter one physics step."""
        assert self.filter is not None, "FilterHook.reset() was not called"
        centers, radii = sim.obstacles
        du, res = self.filter.step(
            sim.kin,
            sim.u,
            sim.theta,
            nominal_du,
            sim.lo,
            sim.hi,
            reference=(sim.reference[0], sim.reference[1]),
            obstacles=(centers, radii) if radii.size else None,
        )
        self.last_result = res
        self.intervened |= res.intervened
        self.avoiding |= res.avoiding
        self.triggered |= res.triggered
        np.maximum(self.correction, res.correction, out=self.correction)
        if _SEVERITY.get(res.status, 2) > _SEVERITY.get(self.status, 2):
            self.status, self.message = res.status, res.message
        self.slack = max(self.slack, res.slack)
        self.solve_time += res.solve_time
        self.iterations += res.iterations
        self.applied = du
        return du

    # what the env and the recorder read ------------------------------------------
    @property
    def last_correction(self) -> np.ndarray:
        """Per-robot correction of the last env step (used by ``RewardConfig.correction``)."""
        return self.correction

    @property
    def last_avoiding(self) -> np.ndarray:
        """Robots in collision avoidance during the last env step (highlighted when rendering)."""
        return self.avoiding

    def record(self) -> dict[str, Any]:
        """Fields for :class:`~aasoatt_env.analysis.recording.RecordEpisode`."""
        return {
            "avoiding": self.avoiding.copy(),
            "triggered": self.triggered.copy(),
            "solver_status": self.status,
            "slack": self.slack,
            "solve_time": self.solve_time,
            "actions": self.applied / self.base.team.max_wheel_accel[:, None],
        }

    def info(self, index: int) -> dict[str, Any]:
        """The ``infos[agent]["filter"]`` dict of robot ``index``."""
        return {
            "intervened": bool(self.intervened[index]),
            "avoiding": bool(self.avoiding[index]),
            "triggered": bool(self.triggered[index]),
            "correction": float(self.correction[index]),
            "status": self.status,
            "slack": float(self.slack),
            "solve_time": float(self.solve_time),
            "iterations": int(self.iterations),
            "n_rows": int(self.last_result.n_rows) if self.last_result is not None else 0,
            "n_qp_rows": int(self.last_result.n_qp_rows) if self.last_result is not None else 0,
        }


class AASOATTFilter(BaseParallelWrapper):
    """Filter every physics step of a parallel env through the AA-SOATT CBF-QP.

    Parameters
    ----------
    env : AASOATTParallelEnv or a wrapper of it
        The env to protect.
    barrier : str
        ``"aasoatt"`` (eqn.7-8, default), ``"braking"``, ``"distance"``,
        ``"gated_distance"``, ``"adaptive_distance"``.
    deadlock : str
        ``"auxiliary_velocity"`` (eqn.13, default), ``"none"``,
        ``"rotate_nominal"``, ``"rotate_reference_velocity"``,
        ``"rotate_relative_position"``.
    trigger : str
        ``"multiplier"`` (default), ``"low_speed"``, ``"stalled"``, ``"heading"``.
    solver : str
        ``"proxsuite"`` (default), ``"neural"``, or another installed solver.
    config : FilterConfig, optional
        A ready configuration; ``**gains`` override its fields.
    **gains
        Any other :class:`~aasoatt_env.safety.config.FilterConfig` field
        (``k1``, ``k2``, ``k3``, ``k4``, ``zeta``, ``rotation_deg``,
        ``sensing_range``, ``safety_margin``, ...).  ``dt`` is taken from the env.
    """

    def __init__(
        self,
        env: Any,
        barrier: str = "aasoatt",
        deadlock: str = "auxiliary_velocity",
        trigger: str = "multiplier",
        solver: str = "proxsuite",
        config: FilterConfig | None = None,
        **gains: Any,
    ) -> None:
        super().__init__(env)
        base = env.unwrapped
        fields = dict(barrier=barrier, deadlock=deadlock, trigger=trigger, solver=solver, dt=base.dt, **gains)
        if config is not None:
            from dataclasses import asdict

            fields = {**asdict(config), **gains, "dt": base.dt}
        self.config = FilterConfig(**fields)  # validated once, errors name the field
        self.hook = FilterHook(base, self.config)
        base.set_control_filter(self.hook)
        if not base.clip_actions:
            base.action_range = "nominal"

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env (and the filter's warm start and deadlock memory)."""
        obs, infos = self.env.reset(seed=seed, options=options)
        return obs, self._add(infos)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Step with ``actions`` as the nominal; the applied ones are filtered."""
        self.hook.begin_step()
        obs, rew, term, trunc, infos = self.env.step(actions)
        return obs, rew, term, trunc, self._add(infos)

    def _add(self, infos: dict[str, dict]) -> dict[str, dict]:
        idx = self.env.unwrapped._index
        for agent, info in infos.items():
            info["filter"] = self.hook.info(idx[agent])
        return infos

    @property
    def last_result(self) -> FilterResult | None:
        """The :class:`FilterResult` of the last physics step."""
        return self.hook.last_result
