"""``ShardedBatchedEnv``: the teams of a batch in worker processes give the batch's answers, errors name the team."""

from __future__ import annotations

import os
import signal
import time

import cloudpickle
import numpy as np
import pytest

from aasoatt_env import AASOATTFilter, make_env
from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded, ScenarioError, UsageError
from aasoatt_env.sim.batched import BatchedAASOATTEnv
from aasoatt_env.sim.sharded import ShardedBatchedEnv, shard_sizes


def _fns(k: int, **kw):
    kw = {"decision_interval": 5, **kw}
    return [lambda: make_env("random_goals", num_robots=4, **kw) for _ in range(k)]


def _interrupt_next_read(sharded):
    """Make the next reply read raise KeyboardInterrupt (Ctrl-C while waiting); returns the undo."""
    receive, calls = sharded._receive, []

    def interrupted(w):
        if not calls:
            calls.append(w)
            raise KeyboardInterrupt
        return receive(w)

    sharded._receive = interrupted
    return lambda: setattr(sharded, "_receive", receive)


def _same_steps(a, b, steps: int, rng, exact: bool = True) -> tuple[int, int]:
    """Step both with the same random actions; every array of every step equal. Team resets and dead slot-steps."""
    resets = dead = 0
    for _ in range(steps):
        act = rng.uniform(-1.0, 1.0, (a.num_envs, a.num_agents, 2))
        ra, rb = a.step(act), b.step(act)
        for x, y in zip(ra[:4], rb[:4]):
            if exact:
                np.testing.assert_array_equal(x, y)
            else:
                np.testing.assert_allclose(x, y, rtol=0, atol=1e-9)
        assert ra[4].keys() == rb[4].keys()
        for key in rb[4]:
            np.testing.assert_array_equal(ra[4][key], rb[4][key]) if exact else np.testing.assert_allclose(
                ra[4][key], rb[4][key], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(a.live, b.live)
        resets += int(rb[4].get("_final_obs", np.zeros(1, bool)).sum())
        dead += int((~b.live).sum())
    return resets, dead


def test_shards_are_bit_identical_to_one_batch_with_resets_and_dead_slots():
    """5 teams in 2 workers (3 + 2), short horizon (resets inside step), collisions end agents (dead slots)."""
    kw = dict(max_steps=6, terminate_on_collision=True, arena_size=3.5, decision_interval=20)
    sharded = ShardedBatchedEnv(_fns(5, **kw), 2)
    try:
        assert sharded.sizes == [3, 2]
        one = BatchedAASOATTEnv(_fns(5, **kw))
        oa, _ = sharded.reset(seed=7)
        ob, _ = one.reset(seed=7)
        np.testing.assert_array_equal(oa, ob)
        resets, dead = _same_steps(sharded, one, 25, np.random.default_rng(0))
        assert resets >= 10  # every team reset at least twice inside step
        assert dead >= 1  # an agent ended by a collision, its slot dead until its team's reset
        np.testing.assert_array_equal(sharded.elapsed_steps, one.elapsed_steps)
        np.testing.assert_array_equal(sharded.max_steps, one.max_steps)
    finally:
        sharded.close()


def test_shards_behind_the_filter_give_the_batch_answers():
    """Behind the default (grouped) filter, and with one call per team and the exact ldp solver."""
    for kw, group, exact in ((dict(filter=True), True, False), (dict(filter={"solver": "ldp"}), False, True)):
        sharded = ShardedBatchedEnv(_fns(4, **kw), 2, group_filter=group)
        try:
            one = BatchedAASOATTEnv(_fns(4, **kw), group_filter=group)
            np.testing.assert_array_equal(sharded.reset(seed=3)[0], one.reset(seed=3)[0])
            _same_steps(sharded, one, 8, np.random.default_rng(1), exact=exact)
            assert sharded.filtered and sharded.grouped_filter is None
        finally:
            sharded.close()


def test_shards_behind_the_default_filter_one_call_per_team_are_bit_identical():
    """docs/env.md: without the grouped filter each team's filter is its own, so the default solver's shards give
    one process's bits (the grouped filter solves a team with its shard-mates: to rounding only)."""
    kw = dict(filter=True, decision_interval=20, action_mode="point")
    sharded = ShardedBatchedEnv(_fns(4, **kw), 2, group_filter=False)
    try:
        one = BatchedAASOATTEnv(_fns(4, **kw), group_filter=False)
        np.testing.assert_array_equal(sharded.reset(seed=0)[0], one.reset(seed=0)[0])
        _same_steps(sharded, one, 40, np.random.default_rng(0))
    finally:
        sharded.close()


def test_per_team_seeds_options_and_the_team_envs():
    sharded = ShardedBatchedEnv(_fns(3), 3)
    try:
        one = BatchedAASOATTEnv(_fns(3))
        seeds, opts = [5, None, 9], [None, {}, None]
        np.testing.assert_array_equal(sharded.reset(seed=seeds, options=opts)[0][[0, 2]],
                                      one.reset(seed=seeds, options=opts)[0][[0, 2]])
        assert sharded.env_get(2, "num_agents") == 4
        sharded.env_set(1, "render_mode", "rgb_array")
        assert sharded.env_get(1, "render_mode") == "rgb_array" and sharded.env_get(0, "render_mode") is None
        with pytest.raises(ConfigError, match=r"options: got a sequence of 2 entries, expected None, one dict"):
            sharded.reset(seed=0, options=[{}, {}])
        np.testing.assert_array_equal(sharded.env_call(2, "state"), one.env_call(2, "state"))
        assert sharded.env_is_wrapped(0, AASOATTFilter) is False
        with pytest.raises(UsageError, match="live in the worker processes"):
            sharded.envs  # noqa: B018
        with pytest.raises(ConfigError, match=r"k: got 3, expected a team number in \[0, 3\)"):
            sharded.env_get(3, "num_agents")
    finally:
        sharded.close()


def test_errors_name_the_argument_and_the_team():
    assert shard_sizes(7, 3) == [3, 2, 2]
    with pytest.raises(ConfigError, match=r"num_workers: got 4, expected an int in \[1, 3\]"):
        ShardedBatchedEnv(_fns(3), 4)
    with pytest.raises(ConfigError, match="start_method"):
        ShardedBatchedEnv(_fns(2), 2, start_method="teleport")
    # a team that cannot be built: the worker's error, raised here with its class
    bad = [lambda: make_env("random_goals", num_robots=4)] + [lambda: make_env("no_such_scene", num_robots=4)]
    with pytest.raises(ScenarioError, match="no_such_scene"):
        ShardedBatchedEnv(bad, 2)
    sharded = ShardedBatchedEnv(_fns(4), 2)
    try:
        with pytest.raises(UsageError, match=r"call reset\(\) first"):
            sharded.step(np.zeros((4, 4, 2)))
        sharded.reset(seed=0)
        with pytest.raises(ActionError, match=r"expected real numbers of shape \(4, 4, 2\)"):
            sharded.step(np.zeros((3, 4, 2)))
        act = np.zeros((4, 4, 2))
        act[3, 1] = np.nan  # team 3 lives in worker 1 as its team 1: the message names team 3
        with pytest.raises(ActionError, match=r"actions\[3, 1\]: got non-finite values"):
            sharded.step(act)
        sharded.step(np.zeros((4, 4, 2)))  # the workers are still in step after an error
    finally:
        sharded.close()
    sharded.close()  # idempotent
    with pytest.raises(UsageError, match="closed"):
        sharded.step(np.zeros((4, 4, 2)))


def test_make_batched_env_with_workers():
    from aasoatt_env import make_batched_env

    with pytest.raises(ConfigError, match=r"num_workers: got 0, expected an integer in \[1, num_envs = 2\]"):
        make_batched_env(2, "random_goals", num_robots=4, num_workers=0)
    with pytest.raises(ConfigError, match="num_robots"):  # checked here, before any worker starts
        make_batched_env(2, "random_goals", num_robots=-1, num_workers=2)
    envs = make_batched_env(3, "random_goals", num_robots=4, num_workers=2, filter=True)
    try:
        assert isinstance(envs, ShardedBatchedEnv) and envs.sizes == [2, 1]
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (3, 4, *envs.agent_observation_space.shape)
        obs, rew, term, trunc, infos = envs.step(np.zeros((3, 4, 2)))
        assert rew.shape == (3, 4) and infos["filter_correction"].shape == (3, 4)
    finally:
        envs.close()


def test_only_one_shard_resetting_gives_the_batch_final_obs():
    """Teams with different horizons: steps where one shard resets and the other does not."""
    fns = [lambda m=m: make_env("random_goals", num_robots=3, decision_interval=5, max_steps=m) for m in (3, 3, 5, 7)]
    sharded, one = ShardedBatchedEnv(fns, 2), BatchedAASOATTEnv(fns)
    try:
        np.testing.assert_array_equal(sharded.reset(seed=1)[0], one.reset(seed=1)[0])
        rng, mixed = np.random.default_rng(0), 0
        for _ in range(12):
            act = rng.uniform(-1, 1, (4, 3, 2))
            ra, rb = sharded.step(act), one.step(act)
            for x, y in zip(ra[:4], rb[:4]):
                np.testing.assert_array_equal(x, y)
            assert ra[4].keys() == rb[4].keys()
            for key in rb[4]:
                np.testing.assert_array_equal(ra[4][key], rb[4][key])
            f = rb[4].get("_final_obs")
            mixed += f is not None and f[:2].any() != f[2:].any()
        assert mixed >= 3
    finally:
        sharded.close()


def test_a_bad_action_or_an_interrupted_call_leaves_the_shards_in_step():
    """No shard steps on a bad action; a call interrupted before its replies were read costs nothing later."""
    sharded, one = ShardedBatchedEnv(_fns(4), 2), BatchedAASOATTEnv(_fns(4))
    try:
        sharded.reset(seed=2)
        one.reset(seed=2)
        act = np.zeros((4, 4, 2))
        act[3, 1] = np.nan
        with pytest.raises(ActionError, match=r"actions\[3, 1\]: got non-finite values"):
            sharded.step(act)
        with pytest.raises(ActionError, match=r"actions\[2, 0\]: got \[2.0, 0.0\], expected values in \[-1, 1\]"):
            sharded.step(np.where(np.arange(4)[:, None, None] == 2, [2.0, 0.0], 0.0) * np.ones((4, 4, 2)))
        with pytest.raises(ActionError, match=r"got shape \(4, 4, 2\) \(dtype <U1\)"):
            sharded.step(np.full((4, 4, 2), "a"))
        np.testing.assert_array_equal(sharded.elapsed_steps, one.elapsed_steps)  # nobody stepped
        undo = _interrupt_next_read(sharded)  # Ctrl-C while waiting for the step's replies
        with pytest.raises(KeyboardInterrupt):
            sharded.step(np.zeros((4, 4, 2)))
        undo()
        one.step(np.zeros((4, 4, 2)))  # the workers did step
        np.testing.assert_array_equal(sharded.elapsed_steps, one.elapsed_steps)
        np.testing.assert_array_equal(sharded.reset(seed=5)[0], one.reset(seed=5)[0])
        _same_steps(sharded, one, 3, np.random.default_rng(3))
    finally:
        sharded.close()


def test_finished_teams_without_autoreset_are_all_named_and_nothing_steps():
    sharded = ShardedBatchedEnv(_fns(4, max_steps=2), 2, autoreset=False)
    try:
        sharded.reset(seed=0)
        for _ in range(2):
            sharded.step(np.zeros((4, 4, 2)))
        with pytest.raises(ResetNeeded, match=r"team\(s\) \[0, 1, 2, 3\] finished their episode"):
            sharded.step(np.zeros((4, 4, 2)))
        np.testing.assert_array_equal(sharded.elapsed_steps, [2, 2, 2, 2])
    finally:
        sharded.close()


def test_the_batch_api_settings_checked_across_shards_and_worker_failures():
    one = BatchedAASOATTEnv(_fns(3))
    sharded = ShardedBatchedEnv(_fns(3), 2)
    try:
        for name in ("observation_space", "action_space", "single_observation_space", "single_action_space",
                     "agent_observation_space", "agent_action_space", "action_mode", "reward_config",
                     "terminate_on_collision", "collision_tolerance", "dt", "decision_interval", "possible_agents"):
            assert getattr(sharded, name) == getattr(one, name), name
        sharded.reset(seed=0)
        one.reset(seed=0)
        assert sharded.env_get(-1, "num_agents") == one.env_get(-1, "num_agents") == 4
        os.kill(sharded._procs[1].pid, signal.SIGINT)  # Ctrl-C reaches every process of the group: ignored
        time.sleep(0.3)
        sharded.step(np.zeros((3, 4, 2)))
        os.kill(sharded._procs[1].pid, signal.SIGKILL)
        sharded._procs[1].join(5.0)
        with pytest.raises(UsageError, match=r"worker 1 \(teams 2..2\) died with exit code -9"):
            sharded.step(np.zeros((3, 4, 2)))
    finally:
        sharded.close()
    mixed = _fns(2) + [lambda: make_env("random_goals", num_robots=4, decision_interval=7)]
    with pytest.raises(ConfigError, match=r"env_fns\[2\]: decision_interval differs from env 0's \(7 vs 5\)"):
        ShardedBatchedEnv(mixed, 2)


def test_an_interrupted_step_still_books_live_without_autoreset():
    """Teams of 5, 5 | 2, 2 decisions: the step that finishes teams 2 and 3 is interrupted before its replies
    are read; the next step still knows they finished (their replies' ``live`` is read then) and steps no team."""
    fns = [lambda m=m: make_env("random_goals", num_robots=4, decision_interval=5, max_steps=m) for m in (5, 5, 2, 2)]
    sharded = ShardedBatchedEnv(fns, 2, autoreset=False)
    try:
        sharded.reset(seed=0)
        sharded.step(np.zeros((4, 4, 2)))
        undo = _interrupt_next_read(sharded)
        with pytest.raises(KeyboardInterrupt):
            sharded.step(np.zeros((4, 4, 2)))
        undo()
        with pytest.raises(ResetNeeded, match=r"team\(s\) \[2, 3\] finished"):
            sharded.step(np.zeros((4, 4, 2)))
        np.testing.assert_array_equal(sharded.elapsed_steps, [2, 2, 2, 2])
        np.testing.assert_array_equal(sharded.live.any(axis=1), [True, True, False, False])
    finally:
        sharded.close()


def test_interrupts_at_any_moment_give_right_answers_or_say_the_env_is_broken():
    """SIGALRM raising KeyboardInterrupt at 20-80% of a 16 MB reply's time, many times: an interrupted call
    raises; every answer after it is right, or (a message cut in two) every call says the env is broken;
    the signal handlers are the caller's throughout (never swapped)."""
    sharded = ShardedBatchedEnv(_fns(2), 2)
    previous, before = signal.getsignal(signal.SIGALRM), signal.getsignal(signal.SIGINT)
    try:
        sharded.reset(seed=0)
        big = np.arange(2_000_000, dtype=np.float64)
        sharded.env_set(0, "big", big)
        t = time.perf_counter()
        sharded.env_get(0, "big")
        dt = time.perf_counter() - t

        def boom(*_):
            raise KeyboardInterrupt

        signal.signal(signal.SIGALRM, boom)
        outcomes = {"interrupted": 0, "right": 0, "broken": 0}
        for frac in np.linspace(0.1, 0.9, 12):
            signal.setitimer(signal.ITIMER_REAL, frac * dt)
            try:
                got = sharded.env_get(0, "big")
                time.sleep(2 * dt)  # an interrupt after the call lands here
            except KeyboardInterrupt:
                outcomes["interrupted"] += 1
                continue
            except UsageError as err:  # an earlier interrupt cut a message in two
                assert "cannot be trusted" in str(err)
                outcomes["broken"] += 1
                break
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            np.testing.assert_array_equal(got, big)  # never a wrong answer
            outcomes["right"] += 1
        assert outcomes["interrupted"] >= 1
        assert signal.getsignal(signal.SIGALRM) is boom and signal.getsignal(signal.SIGINT) is before
        try:
            np.testing.assert_array_equal(sharded.env_get(0, "big"), big)
            sharded.step(np.zeros((2, 4, 2)))
        except UsageError as err:  # a message was cut in two: every call says so
            assert "cannot be trusted" in str(err)
            with pytest.raises(UsageError, match="cannot be trusted"):
                sharded.max_steps  # noqa: B018
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        t = time.perf_counter()
        sharded.close()
        assert time.perf_counter() - t < 4.0  # a broken env is stopped at once


def test_a_timeout_while_waiting_a_stale_error_or_an_unreadable_reply_do_not_derail_the_env(monkeypatch):
    """A signal handler's TimeoutError while waiting is not a dead worker; the error a worker sent for an
    interrupted call is not raised by the next, unrelated call; a whole reply that cannot be unpickled is
    that call's error, and the env goes on."""
    sharded = ShardedBatchedEnv(_fns(2), 2)
    try:
        sharded.reset(seed=0)
        conn = sharded._conns[0]
        real_poll, calls = conn.poll, []

        def poll_times_out(*a):
            if not calls:
                calls.append(1)
                raise TimeoutError("a timeout raised by the caller's alarm")
            return real_poll(*a)

        monkeypatch.setattr(conn, "poll", poll_times_out)
        with pytest.raises(TimeoutError):
            sharded.env_get(0, "num_agents")
        monkeypatch.undo()
        assert sharded.env_get(0, "dt") == 0.005 and sharded.max_steps.shape == (2,)  # in step
        undo = _interrupt_next_read(sharded)  # a call whose reply will be an error, interrupted before reading it
        with pytest.raises(KeyboardInterrupt):
            sharded.env_call(0, "no_such_method")
        undo()
        obs, _ = sharded.reset(seed=1)  # not the stale AttributeError
        assert obs.shape[0] == 2
        monkeypatch.setattr(cloudpickle, "loads", lambda data: (_ for _ in ()).throw(ValueError("corrupt")))
        with pytest.raises(UsageError, match=r"its reply could not be read \(ValueError: corrupt\)"):
            sharded.env_get(1, "dt")
        monkeypatch.undo()
        assert sharded.env_get(1, "dt") == 0.005
    finally:
        sharded.close()
