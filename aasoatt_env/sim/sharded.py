"""``ShardedBatchedEnv``: the teams of a batch stepped in several worker processes.

:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv` steps all teams in one
process, with one filter call per physics step for all of them.  That call is
bound by numpy's per-call overhead, not by the number of robots, so a second
core does not help it; splitting the teams over ``W`` processes does: each
worker steps its own shard (contiguous teams, sizes as equal as possible) as a
``BatchedAASOATTEnv`` with its own grouped filter call, and the shards run at
the same time.  This class has the batch's API and concatenates the shards'
answers in team order, so a trainer sees one batch of ``K`` teams.

What is the same as one process: each team has its own scenario generator,
seed (``reset(seed=s)``: team ``k`` gets ``s + k`` wherever it lives), clock
and filter, and the physics is per team, so without a filter, or with
``group_filter=False`` and a QP solver whose answer is a function of the
problem alone, trajectories are bit-identical to one ``BatchedAASOATTEnv``
(``tests/test_sharded.py``).  Behind the grouped filter each shard's stacked QP
is solved in one piece, so answers agree with one process to rounding, as
the grouped call agrees with separate envs.

Workers are started with ``multiprocessing`` (``forkserver`` where the platform
has it, else ``spawn``: no ``fork`` of a process that may hold torch threads);
the env constructors are sent with ``cloudpickle`` (a Gymnasium dependency), so
lambdas and closures work.  An exception in a worker is raised again in the
caller with the same class where it can be pickled (errors of
:mod:`aasoatt_env.errors` can), naming the worker; the worker stays usable.

API: that of :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv` (``reset``,
``step``, ``live``, ``max_steps``, ``elapsed_steps``, ``sync``, ``render``,
``env_get``/``env_set``/``env_call``/``env_is_wrapped``, ``close``), without
``envs`` (the teams' envs live in the workers: use the ``env_*`` methods) and
with ``grouped_filter = None`` (no filter object in this process).
"""

from __future__ import annotations

import multiprocessing as mp
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import cloudpickle
import numpy as np

from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded, UsageError
from aasoatt_env.sim.batched import BatchedAASOATTEnv, per_team_reset_args

__all__ = ["ShardedBatchedEnv", "shard_sizes"]


def shard_sizes(num_envs: int, num_workers: int) -> list[int]:
    """Teams per worker: contiguous shards, sizes differing by at most one (the first ones larger)."""
    q, r = divmod(num_envs, num_workers)
    return [q + (w < r) for w in range(num_workers)]


def _worker(conn: Any, payload: bytes, autoreset: bool, group_filter: bool, offset: int) -> None:
    """A worker's loop: build its shard, then answer commands until ``close`` (or the pipe closes)."""
    try:
        fns = cloudpickle.loads(payload)
        batch = BatchedAASOATTEnv(fns, autoreset=autoreset, group_filter=group_filter, team_offset=offset)
        conn.send(("ok", (batch.num_agents, batch.possible_agents, batch.agent_observation_space,
                          batch.agent_action_space, batch.filtered, batch.dt, batch.decision_interval)))
    except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
        conn.send(_error(exc))
        conn.close()
        return
    while True:
        try:
            cmd, args = conn.recv()
        except (EOFError, OSError):
            break
        try:
            if cmd == "close":
                batch.close()
                conn.send(("ok", None))
                break
            if cmd == "step":
                out = batch.step(args)
                conn.send(("ok", (*out, batch.live)))
            elif cmd == "reset":
                obs, info = batch.reset(seed=args[0], options=args[1])
                conn.send(("ok", (obs, info, batch.live)))
            elif cmd == "state":
                conn.send(("ok", (batch.max_steps, batch.elapsed_steps)))
            elif cmd == "sync":
                batch.sync()
                conn.send(("ok", None))
            elif cmd == "render":
                conn.send(("ok", batch.render()))
            elif cmd == "get":
                conn.send(("ok", batch.env_get(*args)))
            elif cmd == "set":
                conn.send(("ok", batch.env_set(*args)))
            elif cmd == "call":
                k, name, a, kw = args
                conn.send(("ok", batch.env_call(k, name, *a, **kw)))
            elif cmd == "wrapped":
                conn.send(("ok", batch.env_is_wrapped(*args)))
            else:
                conn.send(("error", UsageError(f"worker: unknown command {cmd!r}"), ""))
        except BaseException as exc:  # noqa: BLE001
            conn.send(_error(exc))
    conn.close()


def _error(exc: BaseException) -> tuple[str, BaseException, str]:
    """``("error", exception, traceback)``: the exception itself where it pickles, else a RuntimeError with its text."""
    tb = traceback.format_exc()
    try:
        cloudpickle.loads(cloudpickle.dumps(exc))
        return "error", exc, tb
    except Exception:  # noqa: BLE001 - an exception that does not survive pickling
        return "error", RuntimeError(f"{type(exc).__name__}: {exc}"), tb


class ShardedBatchedEnv:
    """``K`` teams of one scenario stepped in ``num_workers`` processes (see the module docstring).

    Parameters
    ----------
    env_fns : sequence of callables
        As :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`'s; they are called in the
        workers (sent with ``cloudpickle``).
    num_workers : int
        Worker processes, ``1 <= num_workers <= len(env_fns)``.
    autoreset, group_filter : bool
        As :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`'s, for every shard.
    start_method : str, optional
        ``multiprocessing`` start method; default ``forkserver`` where available, else ``spawn``.
    """

    metadata = {"autoreset_mode": "same_step"}
    grouped_filter = None
    """No filter object lives in this process (each worker has its shard's)."""

    def __init__(self, env_fns: Sequence[Callable[[], Any]], num_workers: int, *, autoreset: bool = True,
                 group_filter: bool = True, start_method: str | None = None) -> None:
        k_all = len(env_fns)
        if k_all < 1:
            raise ConfigError(f"env_fns: got {k_all} callables, expected at least 1")
        if isinstance(num_workers, bool) or not isinstance(num_workers, (int, np.integer)) or not (
                1 <= num_workers <= k_all):
            raise ConfigError(f"num_workers: got {num_workers!r}, expected an int in [1, {k_all}] (at most one "
                              "worker per team)")
        methods = mp.get_all_start_methods()
        if start_method is None:
            start_method = "forkserver" if "forkserver" in methods else "spawn"
        elif start_method not in methods:
            raise ConfigError(f"start_method: got {start_method!r}, expected one of {methods}")
        ctx = mp.get_context(start_method)
        self.num_envs = k_all
        self.autoreset = bool(autoreset)
        self.sizes = shard_sizes(k_all, int(num_workers))
        """Teams per worker."""
        self._starts = np.concatenate(([0], np.cumsum(self.sizes))).astype(int)
        self._conns: list[Any] = []
        self._procs: list[Any] = []
        self._closed = False
        try:
            for w in range(len(self.sizes)):
                a, b = self._starts[w], self._starts[w + 1]
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, name=f"aasoatt-shard-{w}", daemon=True,
                                   args=(child, cloudpickle.dumps(list(env_fns[a:b])), self.autoreset,
                                         bool(group_filter), int(a)))
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
            firsts = [self._receive(w) for w in range(len(self.sizes))]
        except BaseException:
            self.close()
            raise
        (self.num_agents, agents, self.agent_observation_space, self.agent_action_space, self._filtered,
         self.dt, self.decision_interval) = firsts[0]
        self.possible_agents: list[str] = list(agents)
        for w, f in enumerate(firsts[1:], 1):
            if list(f[1]) != self.possible_agents or f[2] != self.agent_observation_space or f[4] != self._filtered:
                self.close()
                raise ConfigError(f"env_fns: worker {w}'s teams differ from worker 0's (agents, observation "
                                  "space or filter); a batch shares one setting")
        self._live = np.zeros((k_all, self.num_agents), dtype=bool)
        self._started = False

    # ------------------------------------------------------------------ plumbing
    def _receive(self, w: int) -> Any:
        try:
            msg = self._conns[w].recv()
        except (EOFError, OSError):
            code = self._procs[w].exitcode
            raise UsageError(f"worker {w} (teams {self._starts[w]}..{self._starts[w + 1] - 1}) died"
                             + (f" with exit code {code}" if code is not None else "")) from None
        if msg[0] == "ok":
            return msg[1]
        exc, tb = msg[1], msg[2]
        if isinstance(exc, BaseException):
            if hasattr(exc, "add_note"):  # Python >= 3.11
                exc.add_note(f"(in worker {w}, teams {self._starts[w]}..{self._starts[w + 1] - 1}; its traceback:\n"
                             f"{tb})")
            raise exc
        raise RuntimeError(f"worker {w}: {exc}")

    def _all(self, cmd: str, args: Sequence[Any]) -> list[Any]:
        """Send ``(cmd, args[w])`` to every worker, then collect the answers (raising the first error)."""
        self._check_open()
        for w, conn in enumerate(self._conns):
            conn.send((cmd, args[w]))
        out, first = [], None
        for w in range(len(self._conns)):
            try:
                out.append(self._receive(w))
            except BaseException as exc:  # keep reading the others: every pipe stays in step
                first = first or exc
        if first is not None:
            raise first
        return out

    def _one(self, k: int, cmd: str, args: tuple) -> Any:
        """``cmd`` for the worker of team ``k`` (its local number first in ``args``)."""
        self._check_open()
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < self.num_envs:
            raise ConfigError(f"k: got {k!r}, expected a team number in [0, {self.num_envs})")
        w = int(np.searchsorted(self._starts, k, side="right") - 1)
        self._conns[w].send((cmd, (int(k) - int(self._starts[w]), *args)))
        return self._receive(w)

    def _check_open(self) -> None:
        if self._closed:
            raise UsageError("ShardedBatchedEnv: closed; make a new one")

    def _split(self, arr: np.ndarray) -> list[np.ndarray]:
        return [arr[self._starts[w]:self._starts[w + 1]] for w in range(len(self.sizes))]

    # ------------------------------------------------------------------ the batch's API
    @property
    def filtered(self) -> bool:
        """True when the teams are behind a control filter."""
        return self._filtered

    @property
    def envs(self) -> list[Any]:
        """Not available here: the teams' envs live in the workers (raises :class:`UsageError`)."""
        raise UsageError("ShardedBatchedEnv.envs: the teams' envs live in the worker processes; use env_get, "
                         "env_set, env_call or env_is_wrapped")

    @property
    def live(self) -> np.ndarray:
        """``(K, N)`` bool: agents that act at the next ``step`` (a copy)."""
        return self._live.copy()

    @property
    def max_steps(self) -> np.ndarray:
        """Horizon of each team's current episode in env steps ``(K,)``."""
        return np.concatenate([s[0] for s in self._all("state", [None] * len(self._conns))])

    @property
    def elapsed_steps(self) -> np.ndarray:
        """Env steps taken in each team's current episode ``(K,)``."""
        return np.concatenate([s[1] for s in self._all("state", [None] * len(self._conns))])

    def reset(self, seed: int | Sequence[int | None] | None = None,
              options: dict | Sequence[dict | None] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every team (as :meth:`BatchedAASOATTEnv.reset`: team ``k`` gets ``seed + k``)."""
        seeds, opts = per_team_reset_args(seed, options, self.num_envs)
        out = self._all("reset", [(seeds[a:b], opts[a:b]) for a, b in zip(self._starts[:-1], self._starts[1:])])
        self._live = np.concatenate([o[2] for o in out])
        self._started = True
        return np.concatenate([o[0] for o in out]), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every shard at once with its teams' actions ``(K, N, 2)``; the answers in team order."""
        if not self._started:
            raise ResetNeeded("step(): call reset() first")
        k, n = self.num_envs, self.num_agents
        try:
            arr = np.asarray(actions)
        except (TypeError, ValueError):
            raise ActionError(f"actions: got {type(actions).__name__}, expected an array ({k}, {n}, 2)") from None
        if arr.size != k * n * 2 or arr.shape not in ((k, n, 2), (k * n, 2)):
            raise ActionError(f"actions: got shape {arr.shape} (dtype {arr.dtype}), expected real numbers of "
                              f"shape ({k}, {n}, 2)")
        out = self._all("step", self._split(arr.reshape(k, n, 2)))
        obs, rew, term, trunc = (np.concatenate([o[i] for o in out]) for i in range(4))
        self._live = np.concatenate([o[5] for o in out])
        infos: dict[str, Any] = {}
        for key in out[0][4]:
            if key not in ("final_obs", "_final_obs"):
                infos[key] = np.concatenate([o[4][key] for o in out])
        if any("_final_obs" in o[4] for o in out):  # a shard without a reset: its obs are its final ones
            parts = [(o[4]["final_obs"], o[4]["_final_obs"]) if "_final_obs" in o[4]
                     else (o[0], np.zeros(o[0].shape[0], dtype=bool)) for o in out]
            infos["final_obs"] = np.concatenate([p[0] for p in parts])
            infos["_final_obs"] = np.concatenate([p[1] for p in parts])
        return obs, rew, term, trunc, infos

    def sync(self) -> None:
        """Write each shard's state into its teams' own envs (in the workers)."""
        self._all("sync", [None] * len(self._conns))

    def render(self) -> tuple[Any, ...]:
        """One frame per team, in team order."""
        return tuple(f for frames in self._all("render", [None] * len(self._conns)) for f in frames)

    def env_get(self, k: int, name: str) -> Any:
        """Attribute ``name`` of team ``k``'s own env (sent back pickled)."""
        return self._one(k, "get", (name,))

    def env_set(self, k: int, name: str, value: Any) -> None:
        """Set attribute ``name`` of team ``k``'s own env."""
        self._one(k, "set", (name, value))

    def env_call(self, k: int, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call method ``name`` of team ``k``'s own env after its shard's ``sync``; its answer."""
        return self._one(k, "call", (name, args, kwargs))

    def env_is_wrapped(self, k: int, wrapper_class: type) -> bool:
        """Whether team ``k``'s own env is (PettingZoo-)wrapped by ``wrapper_class``."""
        return bool(self._one(k, "wrapped", (wrapper_class,)))

    def close(self) -> None:
        """Close the teams' envs and stop the workers (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for conn in self._conns:
            try:
                conn.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for conn in self._conns:
            try:
                if conn.poll(5.0):
                    conn.recv()
            except (EOFError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=1.0)
        for conn in self._conns:
            conn.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass
