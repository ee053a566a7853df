"""``AASOATTFilter``: the CBF-QP safety filter as a drop-in PettingZoo wrapper.

Actions become the *nominal* (outside ``[-1, 1]`` unclipped; the input bounds stay hard); every physics step is filtered
by a :class:`~aasoatt_env.safety.core.SafetyFilter` installed through :mod:`aasoatt_env.sim.protocol`.  Each ``step``'s
:class:`FilterReport` (:attr:`AASOATTFilter.report`) goes into ``infos[agent]["filter"]`` (deterministic; wall times:
:attr:`AASOATTFilter.timing`).  ``infos="flat"`` gives numeric top-level keys for tensor-based clients:
``filter_intervened``, ``filter_avoiding``, ``filter_triggered``, ``filter_backup``, ``filter_correction``,
``filter_status_code`` (the index in :data:`STATUSES`), ``filter_margin``, ``filter_slack``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.core import SafetyFilter
from aasoatt_env.safety.result import STATUSES, FilterResult
from aasoatt_env.sim.env import AASOATTParallelEnv

__all__ = ["STATUS_CODES", "AASOATTFilter", "FilterReport"]

STATUS_CODES: dict[str, int] = {name: code for code, name in enumerate(STATUSES)}  #: ``infos="flat"``; larger: worse


@dataclass(frozen=True)
class FilterReport:
    """The filter over the physics steps of one env step."""

    intervened: np.ndarray  #: ``(N,)`` the filter changed the robot's nominal at some step
    avoiding: np.ndarray  #: ``(N,)`` some barrier row of the robot was active (eta > 0)
    triggered: np.ndarray  #: ``(N,)`` the deadlock strategy acted on the robot
    backup: np.ndarray  #: ``(N,)`` the backup layer braked the robot at some step
    correction: np.ndarray  #: ``(N,)`` largest ``|du_safe - du_nominal|`` [rad/s^2]
    status: str  #: worst status of the team: solved < relaxed < backup < failed < unsafe
    safe: bool  #: the team stayed inside the safe set (status != unsafe)
    margin: float  #: smallest backup margin [m] (``FilterResult.margin``)
    barrier_min: float  #: smallest barrier value ``h``
    message: str  #: the worst step's
    slack: float  #: largest row relaxation (0 unless ``relaxed``)
    iterations: int  #: total solver iterations
    n_rows: int  #: barrier rows at the last physics step
    n_qp_rows: int  #: of those, the rows the QP solver saw (0: closed form)
    applied: np.ndarray  #: ``(N, 2)`` wheel accelerations applied at the last physics step
    solve_time: float  #: the filter's wall time [s] (not in the infos: it is not deterministic)

    @classmethod
    def of(cls, results: tuple[FilterResult, ...]) -> FilterReport:
        """Aggregate the results of the physics steps of one env step."""
        last, worst = results[-1], max(results, key=lambda r: STATUS_CODES[r.status])
        if len(results) == 1:  # (one physics step: its own arrays, without the reductions' cost)
            return cls(last.intervened, last.avoiding, last.triggered, last.backup, last.correction, last.status,
                       last.safe, last.margin, last.barrier_min, last.message, last.slack, last.iterations,
                       last.n_rows, last.n_qp_rows, last.du, last.solve_time)
        flags = ("intervened", "avoiding", "triggered", "backup")
        return cls(*(np.any([getattr(r, k) for r in results], axis=0) for k in flags),
                   correction=np.max([r.correction for r in results], axis=0), status=worst.status,
                   safe=all(r.safe for r in results), margin=min(r.margin for r in results),
                   barrier_min=min(r.barrier_min for r in results), message=worst.message,
                   slack=max(r.slack for r in results), iterations=sum(r.iterations for r in results),
                   n_rows=last.n_rows, n_qp_rows=last.n_qp_rows, applied=last.du,
                   solve_time=sum(r.solve_time for r in results))

    def info(self, index: int) -> dict[str, Any]:
        """The nested ``infos[agent]["filter"]`` dict of robot ``index``."""
        return self.infos(np.array([index]))[0]

    def flat_info(self, index: int) -> dict[str, float]:
        """The numeric top-level keys of ``infos="flat"`` for robot ``index``."""
        return self.flat_infos(np.array([index]))[0]

    def infos(self, indices: np.ndarray | slice) -> list[dict[str, Any]]:
        """The nested ``infos[agent]["filter"]`` dicts of robots ``indices`` (one conversion per field)."""
        shared = {"status": self.status, "safe": bool(self.safe), "margin": float(self.margin),
                  "barrier_min": float(min(self.barrier_min, _BIG)), "slack": float(self.slack),
                  "iterations": int(self.iterations), "n_rows": int(self.n_rows), "n_qp_rows": int(self.n_qp_rows)}
        cols = self._columns(indices)
        return [dict(shared, intervened=a, avoiding=b, triggered=c, backup=d, correction=e)
                for a, b, c, d, e in zip(*cols)]

    def flat_infos(self, indices: np.ndarray | slice) -> list[dict[str, float]]:
        """The numeric top-level keys of ``infos="flat"`` for robots ``indices``."""
        shared = {"filter_status_code": float(STATUS_CODES[self.status]), "filter_margin": float(self.margin),
                  "filter_slack": float(self.slack)}
        cols = self._columns(indices)
        return [{"filter_intervened": float(a), "filter_avoiding": float(b), "filter_triggered": float(c),
                 "filter_backup": float(d), "filter_correction": e, **shared}
                for a, b, c, d, e in zip(*cols)]

    def _columns(self, indices: np.ndarray | slice) -> tuple[list, ...]:
        """The per-robot fields of robots ``indices`` as Python lists (bools and floats)."""
        flags = (np.asarray(f[indices], dtype=bool).tolist()
                 for f in (self.intervened, self.avoiding, self.triggered, self.backup))
        return (*flags, np.asarray(self.correction[indices], dtype=np.float64).tolist())


class AASOATTFilter(BaseParallelWrapper):
    """Filter every physics step of a parallel env through the AA-SOATT CBF-QP (module docstring).

    ``env``: an :class:`~aasoatt_env.sim.env.AASOATTParallelEnv` or a PettingZoo wrapper of one, not yet behind
    a filter.  ``options`` (:class:`~aasoatt_env.safety.config.FilterConfig` fields) replace those of ``config``;
    ``dt`` is the env's.  ``infos``: ``"nested"`` (``infos[agent]["filter"]``) or ``"flat"`` (``filter_*`` keys).
    """

    def __init__(self, env: Any, config: FilterConfig | dict[str, Any] | None = None, *, infos: str = "nested",
                 **options: Any) -> None:
        base = getattr(env, "unwrapped", None)
        if not isinstance(base, AASOATTParallelEnv):
            raise ConfigError(f"env: got {type(env).__name__}, expected an aasoatt_env parallel env "
                              "(AASOATTParallelEnv or a PettingZoo wrapper of it)")
        if "dt" in options:
            raise ConfigError(f"dt: got {options['dt']!r}; the filter runs at the env's physics step ({base.dt:g} s)")
        self._infos_mode = check.choice("infos", infos, ("nested", "flat"))
        cfg = FilterConfig.merged(config, **options)
        if cfg.dt != base.dt:
            cfg = FilterConfig.merged(cfg, dt=base.dt)
        super().__init__(env)
        self.config = cfg
        self.filter = SafetyFilter(config=cfg)
        base.set_control_filter(self.filter)  # raises UsageError if the env already has a filter
        self._report: FilterReport | None = None
        self._time, self._steps = 0.0, 0

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env (and the filter's warm start and deadlock memory)."""
        obs, infos = self.env.reset(seed=seed, options=options)
        self._report = None
        return obs, self._add(infos)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Step with ``actions`` as the nominal; the applied ones are filtered."""
        obs, rew, term, trunc, infos = self.env.step(actions)
        outputs = self.unwrapped.filter_outputs
        self._report = FilterReport.of(outputs) if outputs else None
        if self._report is not None:
            self._time += self._report.solve_time
            self._steps += len(outputs)
        return obs, rew, term, trunc, self._add(infos)

    def _add(self, infos: dict[str, dict]) -> dict[str, dict]:
        rep, base = self._report, self.unwrapped
        if rep is None:
            rep, rows = _IDLE, np.zeros(len(infos), dtype=np.intp)
        elif list(infos) == base.possible_agents:  # every agent, in order: every row
            rows = _ALL_ROWS
        else:
            rows = np.fromiter((base.agent_index[a] for a in infos), dtype=np.intp, count=len(infos))
        if self._infos_mode == "flat":
            for info, add in zip(infos.values(), rep.flat_infos(rows)):
                info.update(add)
        else:
            for info, add in zip(infos.values(), rep.infos(rows)):
                info["filter"] = add
        return infos

    @property
    def report(self) -> FilterReport | None:
        """The :class:`FilterReport` of the last env step (None after ``reset``)."""
        return self._report

    @property
    def last_result(self) -> FilterResult | None:
        """The :class:`~aasoatt_env.safety.core.FilterResult` of the last physics step."""
        outputs = self.unwrapped.filter_outputs
        return outputs[-1] if outputs else None

    @property
    def timing(self) -> dict[str, float]:
        """Filter wall time since construction: ``total_s``, ``physics_steps``, ``mean_ms`` (not deterministic)."""
        return {"total_s": self._time, "physics_steps": float(self._steps),
                "mean_ms": 1e3 * self._time / self._steps if self._steps else 0.0}


_ALL_ROWS = slice(None)  # FilterReport.infos' rows when the infos hold every agent in order (no gather)
_BIG = 1e9  # stands in for an infinite barrier value (no rows): infos stay finite
_IDLE = FilterReport(*(np.zeros(1, dtype=bool),) * 4, np.zeros(1), "solved", True, _BIG, _BIG, "", 0.0, 0, 0, 0,
                     np.zeros((1, 2)), 0.0)  # the infos before a step
