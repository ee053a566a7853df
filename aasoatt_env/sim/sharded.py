"""``ShardedBatchedEnv``: a batch's teams stepped in worker processes, with the batch's API (``docs/env.md``)."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import signal
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import cloudpickle
import numpy as np

from aasoatt_env.errors import ConfigError, UsageError
from aasoatt_env.sim import batched

__all__ = ["ShardedBatchedEnv", "shard_sizes"]


def shard_sizes(num_envs: int, num_workers: int) -> list[int]:
    """Teams per worker: contiguous shards, sizes differing by at most one (the first ones larger)."""
    q, r = divmod(num_envs, num_workers)
    return [q + (w < r) for w in range(num_workers)]


def _reply(conn: Any, msg: Any) -> None:
    """Send ``msg``; one that cannot be pickled goes back as an error saying so (the pipe stays in step)."""
    try:
        data = cloudpickle.dumps(msg)
    except Exception as exc:  # noqa: BLE001 - whatever the pickler raises
        data = cloudpickle.dumps(("error", RuntimeError(f"the answer cannot be sent back ({type(exc).__name__}: "
                                                        f"{exc})"), ""))
    conn.send_bytes(data)


def _error(exc: BaseException) -> tuple[str, BaseException, str]:
    """``("error", exception, traceback)``: the exception itself where it pickles, else a RuntimeError with its text."""
    tb = traceback.format_exc()
    try:
        cloudpickle.loads(cloudpickle.dumps(exc))
        return "error", exc, tb
    except Exception:  # noqa: BLE001 - an exception that does not survive pickling
        return "error", RuntimeError(f"{type(exc).__name__}: {exc}"), tb


def _worker(conn: Any, payload: bytes, autoreset: bool, group_filter: bool, offset: int) -> None:
    """A worker's loop: build its shard, then answer commands until ``close`` (or the pipe closes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's to handle (it closes the workers)
    try:
        batch = batched.BatchedAASOATTEnv(cloudpickle.loads(payload), autoreset=autoreset, group_filter=group_filter,
                                  team_offset=offset)
        space = (batch.agent_observation_space, batch.agent_action_space)
        _reply(conn, ("ok", (batch.shared_settings, batch.nominal_actions, space)))
    except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
        _reply(conn, _error(exc))
        conn.close()
        return
    handlers: dict[str, Callable[[Any], Any]] = {
        "step": lambda a: (*batch.step(a), batch.live),
        "reset": lambda a: (*batch.reset(seed=a[0], options=a[1]), batch.live),
        "state": lambda a: (batch.max_steps, batch.elapsed_steps),
        "sync": lambda a: batch.sync(),
        "render": lambda a: batch.render(),
        "team": lambda a: batch._on_team(*a),
    }
    while True:
        try:
            cmd, args = cloudpickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            break
        try:
            if cmd == "close":
                batch.close()
                _reply(conn, ("ok", None))
                break
            if cmd not in handlers:
                raise UsageError(f"worker: unknown command {cmd!r}")
            _reply(conn, ("ok", handlers[cmd](args)))
        except Exception as exc:  # noqa: BLE001 - reported; the worker goes on
            _reply(conn, _error(exc))
    conn.close()


class _LinkDown(UsageError):
    """A worker died: every later call fails (a reply of an interrupted call is not this)."""


class ShardedBatchedEnv(batched.TeamsAPI):
    """``K`` teams stepped in ``1 <= num_workers <= K`` processes (``start_method``: ``multiprocessing``'s).

    ``env_fns``, ``autoreset`` and ``group_filter`` are :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`'s.  A
    script that makes one must guard its entry point with ``if __name__ == "__main__":`` (``forkserver``/``spawn``).
    """

    grouped_filter = None  # each worker has its shard's

    def __init__(self, env_fns: Sequence[Callable[[], Any]], num_workers: int, *, autoreset: bool = True,
                 group_filter: bool = True, start_method: str | None = None) -> None:
        self._closed = True  # until the workers run (close() is safe on a half-made object)
        self._conns: list[Any] = []
        self._procs: list[Any] = []
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
        self.sizes = shard_sizes(k_all, int(num_workers))  # teams per worker
        self._starts = [0, *np.cumsum(self.sizes).tolist()]
        self._shards = [slice(a, b) for a, b in zip(self._starts[:-1], self._starts[1:])]  # each worker's teams
        self._pending: list[deque[str]] = [deque() for _ in self.sizes]  # commands sent, replies not yet read
        self._broken: str | None = None  # why the pipes cannot be trusted any more
        self._closed = False
        try:
            for w, shard in enumerate(self._shards):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, name=f"aasoatt-shard-{w}", daemon=True,
                                   args=(child, cloudpickle.dumps(list(env_fns[shard])), self.autoreset,
                                         bool(group_filter), int(shard.start)))
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
                self._pending[w].append("start")  # its start-up report
            firsts = [self._receive(w) for w in range(len(self.sizes))]
            for w, f in enumerate(firsts[1:], 1):  # every setting a batch shares, across the shards too
                batched.check_shared(f[0], firsts[0][0], self._starts[w])
        except BaseException:
            self.close()
            raise
        settings, self.nominal_actions, (agent_obs, agent_act) = firsts[0]
        self._take_settings(settings, agent_obs, agent_act)
        self._live = np.zeros((k_all, self.num_agents), dtype=bool)
        self._started = False

    def _teams(self, w: int) -> str:
        return f"worker {w} (teams {self._starts[w]}..{self._starts[w + 1] - 1})"

    def _dead(self, w: int) -> _LinkDown:
        """Worker ``w`` died: its pending replies are gone, and every later call says so."""
        self._pending[w].clear()
        self._procs[w].join(timeout=1.0)
        code = self._procs[w].exitcode
        return _LinkDown(f"{self._teams(w)} died" + (f" with exit code {code}" if code is not None else "")
                         + "; close this env and make a new one (a script that starts workers must guard its "
                         "entry point with `if __name__ == '__main__':`)")

    def _receive(self, w: int) -> Any:
        """Worker ``w``'s reply to its oldest pending command (its answer, or its error raised here).

        An interrupt while waiting leaves the reply to be read later; one while reading breaks the env.
        """
        conn = self._conns[w]
        try:
            conn.poll(None)
        except (EOFError, OSError) as exc:  # the pipe closed, or e.g. a signal handler's timeout
            if not isinstance(exc, EOFError) and self._procs[w].is_alive():  # nothing was read
                raise
            raise self._dead(w) from None
        try:
            data = conn.recv_bytes()
        except (EOFError, OSError):
            raise self._dead(w) from None
        except BaseException:
            self._broken = f"a call was interrupted while reading the reply of {self._teams(w)}"
            raise
        cmd = self._pending[w].popleft()
        try:
            msg = cloudpickle.loads(data)
        except Exception as exc:  # noqa: BLE001 - a whole reply that cannot be read is that call's error
            raise UsageError(f"{self._teams(w)}: its reply could not be read ({type(exc).__name__}: {exc})") from None
        if msg[0] == "ok":
            if cmd in ("step", "reset"):  # `live` follows every step and reset, read now or drained later
                self._live[self._shards[w]] = msg[1][-1]
            return msg[1]
        exc, tb = msg[1], msg[2]
        if hasattr(exc, "add_note") and tb:  # Python >= 3.11
            exc.add_note(f"(raised in {self._teams(w)}; its traceback:\n{tb})")
        raise exc

    def _drain(self, w: int) -> None:
        """Read and drop the replies of interrupted calls (their ``live`` still booked)."""
        while self._pending[w]:
            self._check_open()
            try:
                self._receive(w)
            except _LinkDown:
                raise
            except Exception:  # noqa: BLE001 - the answer or error of an interrupted call: dropped
                pass

    def _settle(self) -> None:
        self._check_open()
        for w in range(len(self._conns)):
            self._drain(w)

    def _post(self, w: int, msg: tuple) -> None:
        self._drain(w)
        data = cloudpickle.dumps(msg)  # a value that cannot be pickled fails here, before anything is sent
        self._pending[w].append(msg[0])
        try:
            self._conns[w].send_bytes(data)
        except BaseException as exc:  # a dead worker, or interrupted while writing: how much it got is unknown
            if isinstance(exc, OSError) and not self._procs[w].is_alive():
                raise self._dead(w) from None
            self._broken = f"a call was interrupted while sending to {self._teams(w)}"
            raise

    def _all(self, cmd: str, args: Sequence[Any] | None = None) -> list[Any]:
        """Send ``(cmd, args[w])`` (or ``None``) to every worker, then collect the answers (raising the first error)."""
        self._check_open()
        try:
            for w in range(len(self._conns)):
                self._post(w, (cmd, None if args is None else args[w]))
        except _LinkDown:
            raise
        except BaseException:  # interrupted between the sends: some shards may have the command, others not
            if not self._broken and len(self._conns) > 1:
                self._broken = f"a {cmd!r} call was interrupted while it was being sent to the workers"
            raise
        out, first = [], None
        for w in range(len(self._conns)):
            try:
                out.append(self._receive(w))
            except Exception as exc:  # keep reading the others: every reply is read
                first = first or exc
        if first is not None:
            raise first
        return out

    def _on_team(self, k: int, what: str, args: tuple) -> Any:
        self._check_open()
        k = batched.team_index(k, self.num_envs)
        w = int(np.searchsorted(self._starts, k, side="right") - 1)
        self._post(w, ("team", (k - self._starts[w], what, args)))
        return self._receive(w)

    def _check_open(self) -> None:
        if self._closed:
            raise UsageError("ShardedBatchedEnv: closed; make a new one")
        if self._broken:
            raise UsageError(f"ShardedBatchedEnv: {self._broken}, so its pipes cannot be trusted; close it and make a "
                             "new one")

    @property
    def envs(self) -> list[Any]:
        """Not available here: the teams' envs live in the workers (raises :class:`UsageError`)."""
        raise UsageError("ShardedBatchedEnv.envs: the teams' envs live in the worker processes; use env_get, "
                         "env_set, env_call or env_is_wrapped")

    @property
    def live(self) -> np.ndarray:
        """``(K, N)`` bool: agents that act at the next ``step`` (a copy)."""
        if any(self._pending):
            self._settle()
        return self._live.copy()

    @property
    def max_steps(self) -> np.ndarray:
        """Each team's episode horizon in env steps ``(K,)``."""
        return np.concatenate([s[0] for s in self._all("state")])

    @property
    def elapsed_steps(self) -> np.ndarray:
        """Env steps taken in each team's episode ``(K,)``."""
        return np.concatenate([s[1] for s in self._all("state")])

    def reset(self, seed: int | Sequence[int | None] | None = None,
              options: dict | Sequence[dict | None] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every team (as :meth:`BatchedAASOATTEnv.reset`: team ``k`` gets ``seed + k``)."""
        seeds, opts = batched.per_team_reset_args(seed, options, self.num_envs)
        out = self._all("reset", [(seeds[shard], opts[shard]) for shard in self._shards])
        self._started = True  # (`live` was taken from the replies)
        return np.concatenate([o[0] for o in out]), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every shard with its teams' actions ``(K, N, 2)`` (checked here first: a bad one steps no team)."""
        self._settle()
        self._check_step(np.flatnonzero(~self._live.any(axis=1)) if not self.autoreset else np.empty(0, np.intp))
        act = batched.parse_actions(actions, self._live, self.nominal_actions, self.shared_settings["clip_actions"])
        act = act.reshape(self.num_envs, self.num_agents, 2)
        out = self._all("step", [act[shard] for shard in self._shards])
        obs, rew, term, trunc = (np.concatenate([o[i] for o in out]) for i in range(4))
        infos: dict[str, Any] = {key: np.concatenate([o[4][key] for o in out]) for key in out[0][4]
                                 if key not in ("final_obs", "_final_obs")}
        if any("_final_obs" in o[4] for o in out):  # a shard without a reset: its obs are its final ones
            parts = [(o[4]["final_obs"], o[4]["_final_obs"]) if "_final_obs" in o[4]
                     else (o[0], np.zeros(o[0].shape[0], dtype=bool)) for o in out]
            infos["final_obs"], infos["_final_obs"] = (np.concatenate(part) for part in zip(*parts))
        return obs, rew, term, trunc, infos

    def sync(self) -> None:
        """Write each shard's state into its teams' own envs (in the workers)."""
        self._all("sync")

    def render(self) -> tuple[Any, ...]:
        """One frame per team, in team order."""
        return tuple(f for frames in self._all("render") for f in frames)

    def close(self, timeout: float = 5.0) -> None:
        """Close the teams' envs and stop the workers (idempotent; any still running after ``timeout`` s is killed)."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + timeout
        try:
            if self._broken:  # the pipes cannot be read in step: stop the workers at once (finally)
                return
            for conn in self._conns:
                with contextlib.suppress(OSError):
                    conn.send_bytes(cloudpickle.dumps(("close", None)))
            for conn in self._conns:  # read whatever is still coming (unread replies, the close's) up to EOF
                with contextlib.suppress(EOFError, OSError):
                    while conn.poll(max(0.0, deadline - time.monotonic())):
                        conn.recv_bytes()
            for proc in self._procs:
                proc.join(timeout=max(0.0, deadline - time.monotonic()))
        finally:
            for proc in self._procs:
                if proc.is_alive():
                    proc.terminate()
                    proc.join(timeout=1.0)
            for conn in self._conns:
                conn.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown
            self.close()
