"""Batched stepping (aasoatt_env.sim.batched): bit-identical to the same teams stepped one by one."""

from __future__ import annotations

import numpy as np
import pytest

from aasoatt_env.api.factory import make_batched_env, make_env
from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded


def _compare(k: int, steps: int, scenario: str = "random_goals", filt=None, seed: int = 7, scale: float = 1.0,
             group_filter: bool = False, **kw) -> dict[str, int]:
    """Step a batch and ``k`` separate envs with the same seeds and actions; every array must be equal.

    ``group_filter=True``: one filter call for all teams, equal to rounding (``_close``) instead.
    """
    batch = make_batched_env(k, scenario, filter=filt, group_filter=group_filter, **kw)
    assert (batch.grouped_filter is not None) == (group_filter and filt is not None)
    same = _close if group_filter else np.testing.assert_array_equal
    envs = [make_env(scenario, filter=filt, **kw) for _ in range(k)]
    obs_b, _ = batch.reset(seed=seed)
    agents = batch.possible_agents
    for j, env in enumerate(envs):
        o, _ = env.reset(seed=seed + j)
        np.testing.assert_array_equal(obs_b[j], np.stack([o[a] for a in agents]))
    rng = np.random.default_rng(0)
    seen = {"resets": 0, "terminations": 0, "dead_agent_steps": 0, "interventions": 0}
    for t in range(steps):
        live = batch.live
        acts = (scale * rng.uniform(-1, 1, (k, len(agents), 2))).astype(np.float32)
        ob, rb, tb, trb, ib = batch.step(acts)
        final = ib.get("_final_obs", np.zeros(k, dtype=bool))
        for j, env in enumerate(envs):
            assert [a for i, a in enumerate(agents) if live[j, i]] == env.agents
            seen["dead_agent_steps"] += int((~live[j]).sum())
            o, r, te, tr, inf = env.step({a: acts[j, i] for i, a in enumerate(agents) if live[j, i]})
            last = ib["final_obs"][j] if final[j] else ob[j]
            for i, a in enumerate(agents):
                if a not in o:
                    assert not tb[j, i] and not trb[j, i]
                    continue
                where = f"step {t}, team {j}, {a}"
                same(last[i], o[a], err_msg=where)
                same(rb[j, i], r[a], err_msg=where)
                assert (tb[j, i], trb[j, i]) == (te[a], tr[a]), where
                for key in ("tracking_error", "clearance"):
                    same(ib[key][j, i], inf[a][key], err_msg=f"{where}: {key}")
                for key in ("collision", "saturated"):
                    assert ib[key][j, i] == inf[a][key], f"{where}: {key}"
                assert ib["time"][j] == inf[a]["time"]
                if filt is not None:
                    same(ib["filter_correction"][j, i], inf[a]["filter"]["correction"], err_msg=where)
                    assert ib["filter_intervened"][j, i] == inf[a]["filter"]["intervened"], where
                    assert ib["filter_avoiding"][j, i] == inf[a]["filter"]["avoiding"], where
                    seen["interventions"] += int(inf[a]["filter"]["intervened"])
                seen["terminations"] += int(te[a])
            assert final[j] == (not env.agents)
            if not env.agents:  # the batch reset this team inside step(): the env's next reset is the same
                seen["resets"] += 1
                o0, _ = env.reset()
                np.testing.assert_array_equal(ob[j], np.stack([o0[a] for a in agents]))
    batch.close()
    return seen


def _close(actual, desired, err_msg: str = "") -> None:
    np.testing.assert_allclose(actual, desired, rtol=1e-7, atol=1e-9, err_msg=err_msg)


def test_batched_equals_separate_point_actions_with_autoreset():
    seen = _compare(3, 100, decision_interval=20, action_mode="point", num_robots=6, max_steps=30)
    assert seen["resets"] >= 9


def test_batched_equals_separate_terminate_on_collision():
    seen = _compare(2, 60, decision_interval=20, action_mode="wheel", num_robots=5, arena_size=4.0,
                    terminate_on_collision=True, max_steps=25)
    assert seen["terminations"] > 0 and seen["dead_agent_steps"] > 0 and seen["resets"] > 0


def test_batched_equals_separate_obstacles_and_unequal_radii():
    _compare(2, 30, scenario="circle_obstacles", decision_interval=10, action_mode="point")
    _compare(2, 20, decision_interval=5, num_robots=4, robots=["paper", "paper_small", "paper", "paper_small"])


def test_batched_equals_separate_behind_the_filter():
    # quadprog: an answer that is a function of the QP alone (proxsuite's last bits depend on memory addresses)
    seen = _compare(2, 14, filt={"solver": "quadprog"}, decision_interval=20, action_mode="point", num_robots=6,
                    arena_size=5.0, max_steps=10, scale=1.5)
    assert seen["interventions"] > 0 and seen["resets"] == 2


@pytest.mark.parametrize("kw", [
    dict(num_robots=6, arena_size=5.0, max_steps=10, scale=1.5),
    dict(scenario="circle_obstacles", max_steps=8),
    dict(num_robots=4, robots=["paper", "paper_small", "paper", "paper_small"], arena_size=4.0, max_steps=10,
         scale=2.0),
], ids=["random_goals", "obstacles", "unequal_radii"])
def test_grouped_filter_equals_separate_filters_to_rounding(kw):
    # one filter call for all teams: the stacked QP and backup check answer each team's own problem
    seen = _compare(3, 14, filt={}, group_filter=True, decision_interval=20, action_mode="point", **kw)
    assert seen["interventions"] > 0 and seen["resets"] >= 3


def test_batched_api_errors_and_spaces():
    batch = make_batched_env(2, "random_goals", num_robots=3, decision_interval=5)
    assert batch.observation_space.shape == (2, 3, batch.agent_observation_space.shape[0])
    assert batch.action_space.shape == (2, 3, 2) and batch.single_action_space.shape == (3, 2)
    with pytest.raises(ResetNeeded):
        batch.step(np.zeros((2, 3, 2)))
    obs, _ = batch.reset(seed=[1, None])
    assert obs.shape == batch.observation_space.shape and obs.dtype == np.float32
    assert batch.live.all()
    with pytest.raises(ActionError, match=r"expected real numbers of shape \(2, 3, 2\)"):
        batch.step(np.zeros((2, 2)))
    with pytest.raises(ActionError, match=r"actions\[1, 2\]: got non-finite"):
        bad = np.zeros((2, 3, 2))
        bad[1, 2, 0] = np.nan
        batch.step(bad)
    with pytest.raises(ActionError, match=r"expected values in \[-1, 1\]"):
        batch.step(np.full((2, 3, 2), 2.0))
    with pytest.raises(ConfigError, match="num_envs"):
        make_batched_env(0)
    batch.sync()  # the teams' own envs now report the batch's state
    np.testing.assert_array_equal(np.stack([e.positions for e in batch.envs]).reshape(-1, 2),
                                  batch._kin.p)  # type: ignore[union-attr]


def test_batched_without_autoreset_asks_for_reset():
    batch = make_batched_env(2, "random_goals", num_robots=2, decision_interval=5, max_steps=2, autoreset=False)
    batch.reset(seed=0)
    batch.step(np.zeros((2, 2, 2)))
    _, _, _, trunc, infos = batch.step(np.zeros((2, 2, 2)))
    assert trunc.all() and "final_obs" not in infos and not batch.live.any()
    with pytest.raises(ResetNeeded, match="finished their episode"):
        batch.step(np.zeros((2, 2, 2)))
