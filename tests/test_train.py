"""Training stack: config validation, VecEnv adapter contract, determinism, smoke train/load/evaluate."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from aasoatt_env.errors import ActionError, ConfigError, DataFileError  # noqa: E402
from aasoatt_env.sim.env import AASOATTParallelEnv  # noqa: E402
from train.config import TRAIN_REWARD, TrainConfig, parse_config  # noqa: E402
from train.vec_env import ParallelVecEnv  # noqa: E402


def tiny(tmp_path, **kw) -> TrainConfig:
    base = dict(
        num_robots=3, n_envs=2, n_steps=16, batch_size=48, n_epochs=2, total_timesteps=2000,
        net_arch=[16, 16], out_dir=str(tmp_path), progress_bar=False, tensorboard=False,
        checkpoint_freq=0, max_steps=30,
    )
    base.update(kw)
    return TrainConfig(**base)


# --------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_robots": 0}, r"TrainConfig.num_robots: got 0, expected an integer in \[1, 65536\]"),
        ({"decision_interval": 2.5}, r"decision_interval: got 2.5, expected an integer in \[1, 10000\]"),
        ({"gamma": 1.5}, r"TrainConfig.gamma: got 1.5, expected a finite number in \[0, 1\]"),
        ({"action_mode": "torque"}, r"action_mode: got 'torque', expected one of \['wheel', 'point'\]"),
        ({"scenario": "nowhere"}, r"scenario: got 'nowhere', expected one of"),
        ({"reward": {"colision": 1.0}},
         r"TrainConfig.reward: got unknown key\(s\) \['colision'\], expected keys among"),
        ({"reward": {"correction": 1.0}}, r"correction=1.0 with filter=False, expected filter=True"),
        ({"net_arch": []}, r"net_arch: got \[\], expected a list of 1 to 16 layer sizes in \[1, 4096\]"),
        ({"net_arch": [8192]}, r"net_arch: got \[8192\], expected a list of 1 to 16 layer sizes"),
        ({"batch_size": 10_000, "n_steps": 8, "n_envs": 1, "num_robots": 2},
         r"batch_size: got 10000, expected at most n_steps \* n_envs \* num_robots = 16"),
        ({"filter": "yes"}, r"TrainConfig.filter: got 'yes', expected true or false"),
        ({"num_workers": 0}, r"TrainConfig.num_workers: got 0, expected an integer in \[1, 256\]"),
        ({"num_workers": 3, "n_envs": 2}, r"num_workers: got 3, expected at most n_envs = 2"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        TrainConfig(**kwargs)


def test_config_file_and_cli(tmp_path):
    toml = tmp_path / "run.toml"
    toml.write_text('num_robots = 4\nseed = 3\n[reward]\ncollision = 20.0\n')
    cfg = parse_config(["--config", str(toml), "--seed", "7", "--reward", "effort=0.1", "--net-arch", "32", "32"])
    assert (cfg.num_robots, cfg.seed, cfg.net_arch) == (4, 7, [32, 32])
    assert cfg.reward == {**TRAIN_REWARD, "collision": 20.0, "effort": 0.1}  # laid over the recipe's reward
    js = tmp_path / "run.json"
    js.write_text(json.dumps({"n_envs": 2, "bogus": 1}))
    with pytest.raises(ConfigError, match=r"got unknown key\(s\) \['bogus'\], expected keys among"):
        TrainConfig.from_file(js)
    with pytest.raises(ConfigError, match=r"config file: got suffix '.yml', expected '.toml' or '.json'"):
        TrainConfig.from_file(tmp_path / "x.yml") if (tmp_path / "x.yml").write_text("a: 1") else None
    with pytest.raises(ConfigError, match=r"--reward: got 'collision', expected KEY=VALUE"):
        parse_config(["--reward", "collision"])


def test_defaults_are_the_shipped_recipe():
    from pathlib import Path

    shipped = TrainConfig.from_file(Path(__file__).resolve().parents[1] / "train/configs/random_goals_6r.toml")
    assert shipped.to_dict() == TrainConfig().to_dict()
    cfg = TrainConfig()
    assert (cfg.policy_prior, cfg.normalize_obs, cfg.normalize_reward, cfg.action_mode) == ("none", True, True, "point")
    assert (cfg.n_envs, cfg.n_steps, cfg.batch_size, cfg.learning_rate, cfg.total_timesteps) == (32, 64, 1024, 3e-4,
                                                                                               1_228_800)
    assert cfg.reward["collision"] == 1.0 and cfg.reward["goal_bonus"] == 0.5 and cfg.reward["goal_tolerance"] == 0.1


# --------------------------------------------------------------------------- VecEnv adapter
def _venv(n_envs=2, **kw):
    kw = {"num_robots": 3, "decision_interval": 20, "max_steps": 5, **kw}
    return ParallelVecEnv([lambda: AASOATTParallelEnv("random_goals", **kw) for _ in range(n_envs)])


def test_vec_env_actions_of_the_wrong_shape_or_nan_name_the_slots():
    """SB3 hands one array for every slot: a wrong shape is refused as such, and a robot's NaN names its team."""
    venv = _venv()
    venv.reset()
    with pytest.raises(ActionError, match=r"actions: got shape \(10,\), expected \(6, 2\) \(one row per slot: "
                       r"2 teams x 3 robots\)"):
        venv.step(np.zeros(10))
    acts = np.zeros((6, 2))
    acts[4, 0] = np.nan  # team 1, robot_1
    with pytest.raises(ActionError, match=r"team 1 \(slots 3..5\): actions\['robot_1'\]: got non-finite"):
        venv.step(acts)


def test_vec_env_truncation_and_autoreset():
    venv = _venv()
    assert venv.num_envs == 6
    venv.seed(123)
    obs = venv.reset()
    assert obs.shape == (6, venv.observation_space.shape[0])
    acts = np.zeros((6, 2), dtype=np.float32)
    for t in range(5):
        venv.step_async(acts)
        obs2, rew, dones, infos = venv.step_wait()
        if t < 4:
            assert not dones.any()
            assert all("terminal_observation" not in i for i in infos)
    assert dones.all()
    assert all(i["TimeLimit.truncated"] is True for i in infos)
    assert all(i["terminal_observation"].shape == obs.shape[1:] for i in infos)
    # auto-reset: the returned observation is a fresh episode's first one
    assert not np.allclose(obs2, np.stack([i["terminal_observation"] for i in infos]))
    venv.close()


def test_vec_env_seeding_reproducible():
    a, b = _venv(), _venv()
    a.seed(5)
    b.seed(5)
    oa, ob = a.reset(), b.reset()
    np.testing.assert_array_equal(oa, ob)
    # env k is seeded with seed + k * n_agents: the two envs differ
    assert not np.allclose(oa[:3], oa[3:])
    a.seed(6)
    assert not np.allclose(a.reset(), ob)


def test_vec_env_dead_slots_terminate_on_collision():
    # two robots driven into each other terminate; the other two keep going until the horizon
    venv = ParallelVecEnv([lambda: AASOATTParallelEnv(
        "position_swap", decision_interval=20, terminate_on_collision=True, max_steps=80, action_mode="point")])
    venv.seed(0)
    obs = venv.reset()
    n = venv.num_envs
    env = venv.envs[0]
    done_count = np.zeros(n, dtype=int)
    dead_steps = 0
    for _ in range(200):
        p = env.unwrapped.positions
        act = np.zeros((n, 2), dtype=np.float32)
        d = p[1] - p[0]
        act[0], act[1] = d / np.linalg.norm(d), -d / np.linalg.norm(d)  # robots 0 and 1 ram each other
        live_before = venv.live_slots
        venv.step_async(act)
        obs, rew, dones, infos = venv.step_wait()
        done_count += dones
        for s in range(n):
            if not live_before[s]:
                dead_steps += 1
                assert infos[s] == {"dead": True} and rew[s] == 0 and not dones[s]
                if not venv.live_slots[s]:  # (after an auto-reset the slot holds the new episode's obs)
                    assert not obs[s].any()
            elif dones[s] and not infos[s]["TimeLimit.truncated"]:
                assert infos[s]["collision"] is True
        if (done_count > 0).all():  # the episode is over (auto-reset happened)
            break
    assert (done_count == 1).all(), "each slot is done exactly once per episode"
    assert dead_steps > 0, "some slot was dead while others kept going"
    assert infos[2]["TimeLimit.truncated"] and infos[3]["TimeLimit.truncated"]


# --------------------------------------------------------------------------- determinism
def _two_updates_checksum(tmp_path, seed: int, **kw) -> float:
    from train.train import build_model, make_vec_env

    cfg = tiny(tmp_path, seed=seed, **kw)
    venv = make_vec_env(cfg)
    model = build_model(cfg, venv)
    model.learn(total_timesteps=2 * cfg.n_steps * venv.num_envs)
    assert model._n_updates == 2 * cfg.n_epochs
    venv.close()
    return float(sum(p.detach().double().sum().item() * (k + 1) for k, p in enumerate(model.policy.parameters())))


def test_same_seed_identical_first_two_updates(tmp_path):
    a = _two_updates_checksum(tmp_path, seed=11)
    b = _two_updates_checksum(tmp_path, seed=11)
    c = _two_updates_checksum(tmp_path, seed=12)
    assert a == b
    assert a != c


def test_worker_processes_train_the_same_first_updates(tmp_path):
    """num_workers = 2: the teams stepped in two processes; the same updates as in one (bare: bit for bit)."""
    one = _two_updates_checksum(tmp_path, seed=11)
    two = _two_updates_checksum(tmp_path, seed=11, num_workers=2)
    assert one == two


# --------------------------------------------------------------------------- smoke: train, save, load, evaluate
def _smoke(tmp_path, filtered: bool):
    from agents.learned import LearnedAgent
    from train.evaluate import evaluate, to_markdown
    from train.train import train

    kw = dict(filter=True, filter_kwargs={"solver": "quadprog"}, reward={"correction": 0.1}) if filtered else {}
    cfg = tiny(tmp_path, run_name="filter" if filtered else "bare", **kw)
    path = train(cfg)
    assert path.is_file() and (path.parent / "normalization.npz").is_file() and (path.parent / "policy.json").is_file()
    assert not list(path.parent.rglob("*.pkl"))  # nothing pickled
    agent = LearnedAgent.load(path)
    env = agent.make_env()
    obs, _ = env.reset(seed=1)
    agent.reset(env)
    acts = agent.act(obs, env)
    assert set(acts) == set(env.agents) and all(a.shape == (2,) for a in acts.values())
    # deterministic: same observations, same actions
    again = agent.act(obs, env)
    assert all(np.array_equal(acts[a], again[a]) for a in acts)
    rows = ["random", "learned (filter) + filter"] if filtered else ["random", "tracking", "learned (bare)"]
    table = evaluate(
        None if filtered else path, path if filtered else None, episodes=1, rows=rows,
        filter_kwargs={"solver": "quadprog"},
    )
    assert [r.name for r in table] == rows
    md = to_markdown(table)
    assert md.count("\n") == len(rows) + 1
    for r in table:
        assert 0.0 <= r.safe_rate <= 1.0 and 0.0 <= r.success_rate <= 1.0 and np.isfinite(r.rmse)
    if not filtered:  # the tracking law tracks far better than random actions, even in one episode
        rmse = {r.name: r.rmse for r in table}
        assert rmse["tracking"] < 0.5 < rmse["random"]
    if filtered:
        assert table[-1].intervention_rate is not None and table[-1].collisions == 0
    else:  # rows in parallel processes: the same numbers
        par = evaluate(path, None, episodes=1, rows=rows, jobs=2)
        assert [(r.name, r.rmse, r.safe_rate, r.collisions) for r in par] == [
            (r.name, r.rmse, r.safe_rate, r.collisions) for r in table
        ]


@pytest.mark.slow
def test_smoke_train_load_evaluate_bare(tmp_path):
    _smoke(tmp_path, filtered=False)


@pytest.mark.slow
def test_smoke_train_load_evaluate_filtered(tmp_path):
    _smoke(tmp_path, filtered=True)


def test_learned_agent_rejects_mismatched_env(tmp_path):
    from agents.learned import LearnedAgent
    from train.train import train

    path = train(tiny(tmp_path, total_timesteps=200, run_name="m"))
    agent = LearnedAgent.load(path.parent)
    env = AASOATTParallelEnv("random_goals", num_robots=3, num_neighbors=2)
    env.reset(seed=0)
    with pytest.raises(ConfigError, match=r"observation shape \(38,\), expected \(50,\)"):
        agent.reset(env)
    with pytest.raises(DataFileError, match=r"nope.zip: no model here"):
        LearnedAgent.load(tmp_path / "nope.zip")


# --------------------------------------------------------------------------- tracking prior / shaping
def test_tracking_prior_matches_tracking_law():
    from agents import TrackingController
    from agents.prior import tracking_prior_matrix

    env = AASOATTParallelEnv("random_goals", num_robots=3, decision_interval=20, action_mode="point")
    obs, _ = env.reset(seed=1)
    for _ in range(3):
        obs, *_ = env.step({a: np.array([0.3, -0.2], dtype=np.float32) for a in env.agents})
    amax = float(env.team.max_point_accel[0])
    w = tracking_prior_matrix(env.observation_space("robot_0").shape[0], 1.0, 4.0, amax)
    expected = TrackingController(1.0, 4.0).point_accel(env) / amax
    got = np.stack([w @ obs[a].astype(np.float64) for a in env.agents])
    np.testing.assert_allclose(got, expected, atol=1e-4)


def test_policy_prior_config_errors():
    with pytest.raises(ConfigError, match=r"expected action_mode='point' and normalize_obs=false"):
        TrainConfig(policy_prior="tracking")
    with pytest.raises(ConfigError, match=r"TrainConfig.policy_prior: got 'pd', expected one of"):
        TrainConfig(policy_prior="pd")
    with pytest.raises(ConfigError, match=r"prior_gains: got \[1.0\], expected two positive numbers"):
        TrainConfig(prior_gains=[1.0])


def test_velocity_tracking_shaping():
    from train.vec_env import VelocityTrackingShaping

    base, shaped = _venv(), VelocityTrackingShaping(_venv(), 2.0)
    base.seed(5)
    shaped.seed(5)
    base.reset()
    shaped.reset()
    act = np.tile(np.array([[0.5, -0.5]], dtype=np.float32), (base.num_envs, 1))
    for _ in range(6):  # crosses the max_steps=5 auto-reset (terminal observation used)
        base.step_async(act)
        shaped.step_async(act)
        o0, r0, d0, i0 = base.step_wait()
        o1, r1, d1, i1 = shaped.step_wait()
        np.testing.assert_array_equal(o0, o1)
        last = np.array([i["terminal_observation"] if d else o for o, d, i in zip(o0, d0, i0)])
        err = np.linalg.norm(last[:, 4:6] - last[:, 10:12], axis=1)
        np.testing.assert_allclose(r1, r0 - 2.0 * err, rtol=1e-5, atol=1e-5)


def test_train_with_tracking_prior_load_act(tmp_path):
    from agents.learned import LearnedAgent
    from train.train import train

    cfg = tiny(tmp_path, action_mode="point", policy_prior="tracking", normalize_obs=False, log_std_init=-3.0,
               total_timesteps=96, learning_rate=1e-9, velocity_tracking=0.5, run_name="prior")
    agent = LearnedAgent.load(train(cfg))
    env = agent.make_env()
    obs, _ = env.reset(seed=3)
    agent.reset(env)
    for _ in range(2):
        obs, *_ = env.step(agent.act(obs, env))
    act = agent.act(obs, env)
    base = env.unwrapped
    w = np.asarray(agent.model.policy.prior.weight.detach().cpu().numpy(), dtype=np.float64)
    # with a ~zero learning rate the policy is still the tracking law plus a near-zero MLP output
    for a in env.agents:
        np.testing.assert_allclose(act[a], np.clip(w @ obs[a], -1, 1), atol=0.05)
    assert base.action_mode == "point"


# --------------------------------------------------------------------------- batched adapter, episode boundaries
def _crowded(tmp_path, **kw) -> TrainConfig:
    """Robots in a small arena with terminate_on_collision: collisions, dead slots, early episode ends."""
    return tiny(tmp_path, num_robots=5, n_envs=2, scenario_kwargs={"arena_size": 4.0}, terminate_on_collision=True,
                action_mode="wheel", max_steps=30, **kw)


def test_episode_lengths_never_above_horizon_with_terminate_on_collision(tmp_path):
    from train.train import make_vec_env

    cfg = _crowded(tmp_path)
    venv = make_vec_env(cfg)
    base = venv.unwrapped
    venv.seed(3)
    venv.reset()
    rng = np.random.default_rng(0)
    lengths, dead, terminated, normalised_rows = [], 0, 0, 0
    for _ in range(150):
        live_before = base.live_slots
        _, _, dones, infos = venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)).astype(np.float32))
        dead += int((~base.acted_slots).sum())
        assert np.array_equal(base.acted_slots, live_before)
        normalised_rows += int(base.live_slots.sum())
        for s in np.flatnonzero(dones):
            lengths.append(infos[s]["episode"]["l"])
            terminated += not infos[s]["TimeLimit.truncated"]
            assert "dead" not in infos[s]
        for s in np.flatnonzero(~base.acted_slots):
            assert infos[s] == {"dead": True} and not dones[s]
    assert dead > 0 and terminated > 0, "the crowded arena must produce collisions and dead slots"
    assert lengths and max(lengths) <= cfg.max_steps
    # the observation statistics saw the real observations only (not the zeros of dead slots)
    assert venv.obs_rms.count == pytest.approx(normalised_rows + venv.num_envs + 1e-4)
    venv.close()


def test_masked_rollout_buffer_drops_padding_and_equals_sb3_without_it():
    from gymnasium import spaces
    from stable_baselines3.common.buffers import RolloutBuffer

    from train.ppo import MaskedRolloutBuffer

    obs_space, act_space = spaces.Box(-1, 1, (3,)), spaces.Box(-1, 1, (2,))
    bufs = [cls(8, obs_space, act_space, n_envs=4) for cls in (MaskedRolloutBuffer, RolloutBuffer, MaskedRolloutBuffer)]
    rng = np.random.default_rng(0)
    for t in range(8):
        obs = rng.normal(size=(4, 3)).astype(np.float32)
        act = rng.normal(size=(4, 2)).astype(np.float32)
        rew = rng.normal(size=4).astype(np.float32)
        for b in bufs:
            if b is bufs[2]:
                b.next_valid = np.array([True, t < 3, True, t >= 5])
            b.add(obs, act, rew, np.zeros(4), torch.zeros(4), torch.zeros(4))
    for b in bufs:
        b.compute_returns_and_advantage(torch.zeros(4), np.zeros(4))
    np.random.seed(1)  # noqa: NPY002 - SB3 draws minibatches from the global generator
    masked_all = [x.observations.numpy() for x in bufs[0].get(5)]
    np.random.seed(1)  # noqa: NPY002 - SB3 draws minibatches from the global generator
    plain = [x.observations.numpy() for x in bufs[1].get(5)]
    assert len(masked_all) == len(plain) and all(np.array_equal(a, b) for a, b in zip(masked_all, plain))
    assert bufs[2].n_valid == 8 + 3 + 8 + 3
    got = np.concatenate([x.observations.numpy() for x in bufs[2].get(4)])
    valid = bufs[2].valid.swapaxes(0, 1).reshape(-1)
    expected = bufs[2].observations[valid]
    assert got.shape == expected.shape
    assert sorted(map(tuple, got.round(6))) == sorted(map(tuple, expected.round(6)))


def test_ppo_trains_only_on_transitions_of_robots_that_acted(tmp_path):
    from train.train import build_model, make_vec_env

    cfg = _crowded(tmp_path, n_steps=64, batch_size=64)
    venv = make_vec_env(cfg)
    model = build_model(cfg, venv)
    acted = []
    orig = model._update_info_buffer

    def spy(infos, dones=None):
        acted.append(venv.unwrapped.acted_slots)
        orig(infos, dones)

    model._update_info_buffer = spy
    model.learn(cfg.n_steps * venv.num_envs)
    buf = model.rollout_buffer
    np.testing.assert_array_equal(buf.valid, np.stack(acted))
    assert 0 < buf.n_valid < buf.valid.size
    assert sum(x.actions.shape[0] for x in buf.get(64)) == buf.n_valid
    venv.close()


# --------------------------------------------------------------------------- telemetry
def test_logged_metrics_present(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from train.telemetry import METRICS, read_metrics
    from train.train import train

    path = train(tiny(tmp_path, filter=True, filter_kwargs={"solver": "quadprog"}, total_timesteps=192,
                      tensorboard=True, run_name="tele"))
    run = path.parent
    rows = read_metrics(run / "metrics.csv")
    assert len(rows) == 2 and rows[-1]["agent_steps"] == 192
    for key in METRICS:
        assert key in rows[-1]
    assert rows[-1]["episodes"] > 0 and 0.0 <= rows[-1]["success_rate"] <= 1.0  # max_steps=30 < 32 steps
    assert rows[-1]["tracking_error"] > 0 and 0.0 <= rows[-1]["intervention_rate"] <= 1.0
    assert rows[-1]["mean_correction"] >= 0.0
    (tb,) = (run / "tb").iterdir()
    acc = EventAccumulator(str(tb))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    for key in ("success_rate", "tracking_error", "collision_rate", "intervention_rate", "mean_correction"):
        assert f"metrics/{key}" in tags
    stats = json.loads((run / "train_stats.json").read_text())
    assert stats["agent_steps"] == 192 and stats["agent_steps_per_s"] > 0
    from aasoatt_env.compiled import available

    assert stats["filter_kernel"] == ("numba" if available() else "numpy")  # "auto" resolved, recorded
    pytest.importorskip("matplotlib")
    assert (run / "learning_curve.png").stat().st_size > 1000


def test_progress_line(capsys):
    from train.telemetry import progress_line

    line = progress_line({"agent_steps": 61440, "agent_steps_per_s": 1000.0, "wall_time_s": 61.0,
                          "success_rate": 0.5, "tracking_error": 0.25, "collision_rate": 0.01,
                          "intervention_rate": 0.2, "mean_correction": 1.5}, total=122880)
    assert line.startswith("[ 50.0%]") and "success 50.0%" in line and "intervention 20.0%" in line
    assert "eta 1m01s" in line


def test_init_from_starts_with_the_runs_weights_and_statistics(tmp_path):
    from agents.learned import LearnedAgent
    from train.train import build_model, init_policy, make_vec_env, train

    src = train(tiny(tmp_path, total_timesteps=192, run_name="src"))
    cfg = tiny(tmp_path, filter=True, filter_kwargs={"solver": "quadprog"}, reward={"correction": 1.0},
               init_from=str(src.parent), run_name="tuned")
    venv = make_vec_env(cfg)
    model = build_model(cfg, venv)
    init_policy(model, venv, cfg)
    agent = LearnedAgent.load(src)
    for k, v in agent.model.policy.state_dict().items():
        assert torch.equal(v, model.policy.state_dict()[k]), k
    np.testing.assert_array_equal(venv.obs_rms.mean, agent.obs_stats[0])
    venv.close()
    with pytest.raises(ConfigError, match=r"net_arch: got \[8\], the init_from run has \[16, 16\]"):
        bad = tiny(tmp_path, net_arch=[8], init_from=str(src.parent), run_name="bad")
        venv = make_vec_env(bad)
        init_policy(build_model(bad, venv), venv, bad)


def test_compare_table_from_results():
    from train.compare import to_markdown

    ev = {"success_rate": 1.0, "rmse": 0.1, "collisions": 0, "collision_episodes": 0, "safe_rate": 1.0,
          "intervention_rate": 0.4, "mean_correction": 10.0, "episodes": 3, "seed": 10000}
    runs = [{"scene": "random_goals_6r", "variant": v, "seed": s, "total_wall_s": 100.0 + s, "train_agent_steps": 10,
             "init_from": None if v == "bare" else f"bare_s{s}", "correction_weight": 0.0 if v == "bare" else 1.0,
             "eval_bare": {**ev, "intervention_rate": None, "mean_correction": None},
             "eval_filter": {**ev, "mean_correction": 10.0 if v == "bare" else 6.0 + s}}
            for v in ("bare", "filter+correction") for s in (0, 2)]
    md = to_markdown({"settings": {"scenes": {"random_goals_6r": {}}, "seeds": [0, 2],
                                   "variants": ["bare", "filter+correction"], "bare_steps": 10, "filter_steps": 5,
                                   "filter_start": "bare", "filter_n_steps": 64, "correction": 1.0, "episodes": 3,
                                   "eval_seed": 10000}, "runs": runs})
    assert "| (a) trained bare | behind the filter | 100.0% ± 0.0 | 0.100 ± 0.000 | 0 (0) | 100.0% ± 0.0 |" in md
    assert "| 7.000 ± 1.000 | 101 ± 1 |" in md
    assert "(c) vs (a) on the same seeds: 7.000 vs 10.000 rad/s^2 (30.0% less)" in md
    assert "(c) seeds 0, 2: fine-tuned from (a) of the same seed for 10 agent-steps, correction weight 1" in md


def test_compare_reuses_a_finished_run_only_if_it_was_trained_with_the_same_settings(tmp_path):
    from train.compare import _train

    run = tmp_path / "bare_s0"
    run.mkdir()
    cfg = tiny(tmp_path, run_name="bare_s0")
    done = cfg.to_dict()
    (run / "model.zip").write_bytes(b"")
    (run / "train_stats.json").write_text(json.dumps({"wall_time_s": 1.0}))
    # bookkeeping fields (where it was written, progress bar, threads) may differ
    (run / "config.json").write_text(json.dumps({**done, "progress_bar": True, "torch_threads": 2}))
    assert _train(run, cfg, None) == {"wall_time_s": 1.0}
    # a run of another recipe (say the default n_envs changed since it was trained) is not reused silently
    (run / "config.json").write_text(json.dumps({**done, "n_envs": 8, "n_steps": 256}))
    with pytest.raises(ConfigError, match=r"bare_s0: a finished run with other settings is in the way: n_envs 8 "
                                          r"\(asked 2\), n_steps 256 \(asked 16\); use another --out-dir"):
        _train(run, cfg, None)
    (run / "config.json").write_text(json.dumps({**done, "reward": {**done["reward"], "correction": 2.0}}))
    with pytest.raises(ConfigError, match=r"in the way: reward.correction 2.0 \(asked None\); use another"):
        _train(run, cfg, None)
    # the same start folder written another way is the same run
    src = tmp_path / "src"
    src.mkdir()
    tuned = tiny(tmp_path, run_name="bare_s0", init_from=str(src))
    (run / "config.json").write_text(json.dumps({**tuned.to_dict(), "init_from": str(tmp_path / "x" / ".." / "src")}))
    assert _train(run, tuned, None) == {"wall_time_s": 1.0}
    (run / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="bare_s0: a finished run without a readable config.json"):
        _train(run, cfg, None)


def test_compare_evaluations_belong_to_the_model_they_evaluated(tmp_path, monkeypatch):
    import train.evaluate
    from train.compare import _evaluate

    run = tmp_path / "bare_s0"
    run.mkdir()
    (run / "model.zip").write_bytes(b"first model")
    calls = []

    class Row:
        def as_dict(self):
            return {"episodes": 2, "success_rate": float(len(calls))}

    def fake(name, agent, make, episodes, seed):
        calls.append(name)
        return Row()

    monkeypatch.setattr(train.evaluate, "evaluate_agent", fake)
    monkeypatch.setattr("agents.learned.LearnedAgent.load", staticmethod(lambda path: None))
    cache = tmp_path / "evals" / "bare_s0_bare.json"
    cfg = tiny(tmp_path)
    assert _evaluate(run, cfg, False, 2, 10_000, cache, None)["success_rate"] == 1.0
    assert _evaluate(run, cfg, False, 2, 10_000, cache, None)["success_rate"] == 1.0  # cached
    assert len(calls) == 1
    (run / "model.zip").write_bytes(b"retrained model")  # removed and retrained: evaluated again
    assert _evaluate(run, cfg, False, 2, 10_000, cache, None)["success_rate"] == 2.0
    assert len(calls) == 2
