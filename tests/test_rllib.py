"""The Ray RLlib backend (``train/rllib.py``, ``agents/rllib_agent.py``) and the README's RLlib commands.

Ray RLlib 2.60 pins gymnasium 1.2.2, so these tests run in the virtual environment of the
``rllib`` extra, which ``.ci/run`` creates with the README's set-up line::

    .venv-rllib/bin/python -m pytest -q -m "slow or not slow" tests/test_rllib.py tests/test_clients.py

Where Ray is not installed the tests that need it are skipped, with that reason; the
configuration and command-line tests run everywhere.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from readme_blocks import readme_block

from aasoatt_env.apps import cli
from aasoatt_env.errors import ConfigError, DataFileError
from train.config import TRAIN_REWARD, unique_run_dir
from train.rllib import RLlibConfig, build_parser, main

HAS_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAS_RAY, reason="Ray RLlib is not installed: it has its own venv from the rllib "
                                                   "extra (README: Use it from your RL library; .ci/run makes it)")
# one PPO iteration of 1,600 agent-steps (4 teams of 4 robots, 100 decisions each), 2 epochs
TINY = ["--iterations", "1", "--num-envs-per-env-runner", "4", "--train-batch-size", "1600", "--minibatch-size", "128",
        "--num-epochs", "2"]
BIN = Path(sys.executable).parent  # the venv's console scripts (aasoatt, ray)


# ---------------------------------------------------------------------------------------------- no Ray needed
def test_config_defaults_file_and_command_line(tmp_path):
    cfg = RLlibConfig()
    assert cfg.filter is True and cfg.num_env_runners == 0 and cfg.address is None
    (tmp_path / "run.toml").write_text('num_robots = 4\niterations = 3\n[filter_kwargs]\nsolver = "ldp"\n')
    args = build_parser().parse_args(["--config", str(tmp_path / "run.toml"), "--iterations", "5",
                                      "--num-env-runners", "2", "--address", "auto", "--reward", "collision=2"])
    from train.config import config_from_args

    cfg = config_from_args(args, RLlibConfig)
    assert (cfg.num_robots, cfg.iterations, cfg.num_env_runners, cfg.address) == (4, 5, 2, "auto")
    assert cfg.filter_kwargs == {"solver": "ldp"} and cfg.reward == {**TRAIN_REWARD, "collision": 2.0}
    ec = cfg.env_config()
    assert ec["env"]["num_robots"] == 4 and ec["filter"]["solver"] == "ldp"
    assert RLlibConfig(filter=False).env_config()["filter"] is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"minibatch_size": 500, "train_batch_size": 400}, r"RLlibConfig.minibatch_size: got 500, expected at most"),
        ({"num_env_runners": -1}, r"RLlibConfig.num_env_runners: got -1, expected an integer in \[0, 256\]"),
        ({"address": "auto", "num_cpus": 2}, r"RLlibConfig.num_cpus: got 2 with address='auto'"),
        ({"scenario": "nowhere"}, r"RLlibConfig.scenario: got 'nowhere'"),
        ({"filter_kwargs": {"barier": "aasoatt"}}, r"RLlibConfig.filter_kwargs: .*barier"),
        ({"net_arch": []}, r"RLlibConfig.net_arch"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        RLlibConfig(**kwargs)


def test_aasoatt_train_backend_rllib_forwards(capsys):
    assert cli.main(["train", "--backend", "rllib", "--num-robots", "4", "--num-env-runners", "3",
                     "--print-config"]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["num_robots"] == 4 and cfg["num_env_runners"] == 3 and cfg["filter"] is True
    assert cli.main(["train", "--backend=rllib", "--num-robots", "0"]) == 2
    assert "RLlibConfig.num_robots: got 0" in capsys.readouterr().err
    assert main(["--print-config", "--seed", "3"]) == 0


@pytest.mark.skipif(HAS_RAY, reason="checks the message shown where Ray is not installed")
def test_without_ray_the_command_says_how_to_install_it(capsys):
    assert cli.main(["train", "--backend", "rllib", "--iterations", "1"]) == 2
    assert "rllib extra" in capsys.readouterr().err


def test_slot_vector_env_is_the_batch_with_next_step_restarts():
    """Every robot a sub-env; the batch's own steps; an episode's end, then its restart after one decision at rest."""
    from aasoatt_env import make_batched_env
    from train.rllib_env import SlotVectorEnv

    env_config = RLlibConfig(num_robots=3, max_steps=5, filter=False).env_config()
    env, ref = SlotVectorEnv(env_config, 6), make_batched_env(2, **env_config["env"])
    assert (env.num_envs, env.teams, env.robots) == (6, 2, 3)
    obs, _ = env.reset(seed=7)
    robs, _ = ref.reset(seed=7)
    assert np.array_equal(obs, robs.reshape(6, -1))
    rng = np.random.default_rng(0)
    for t in range(5):
        a = rng.uniform(-1.5, 1.5, (6, 2)).astype(np.float32)  # (RLlib's actions are float32)
        obs, rew, term, trunc, infos = env.step(a)
        robs, rrew, _, _, rinfo = ref.step(np.clip(a, -1, 1).reshape(2, 3, 2))  # actions clipped as RLlib would
        if t < 4:
            assert np.array_equal(obs, robs.reshape(6, -1)) and np.array_equal(rew, rrew.ravel().astype(np.float32))
            assert not (term | trunc).any() and infos == {}
    assert trunc.all() and not term.any() and np.array_equal(obs, rinfo["final_obs"].reshape(6, -1))
    assert infos["_is_success"].all()
    np.testing.assert_array_equal(infos["is_success"], rinfo["goal_distance"].ravel() <= 0.1)
    obs, rew, term, trunc, infos = env.step(np.full((6, 2), 0.9))  # ignored: the new episodes start at rest
    robs, *_ = ref.step(np.zeros((2, 3, 2)))
    assert np.array_equal(obs, robs.reshape(6, -1)) and not rew.any() and not (term | trunc).any() and infos == {}
    with pytest.raises(ValueError, match="num_envs: got 7, expected a multiple of the team size 3"):
        SlotVectorEnv(env_config, 7)


def test_run_folders_never_overwrite(tmp_path):
    a = unique_run_dir(tmp_path, "run")
    (a / "x").write_text("1")
    b = unique_run_dir(tmp_path, "run")
    c = unique_run_dir(tmp_path, "run")  # b is still empty: reused
    assert (a.name, b.name, c.name) == ("run", "run_2", "run_2")
    (b / "x").write_text("2")
    assert unique_run_dir(tmp_path, "run").name == "run_3"


# ---------------------------------------------------------------------------------------------- one PPO iteration
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """One PPO iteration on RandomGoals with 4 robots behind the filter, through ``aasoatt train --backend rllib``."""
    if not HAS_RAY:
        pytest.skip("Ray RLlib is not installed: it has its own venv from the rllib extra (README; .ci/run makes it)")
    out = tmp_path_factory.mktemp("rllib")
    rc = cli.main(["train", "--backend", "rllib", "--scenario", "random_goals", "--num-robots", "4", *TINY,
                   "--num-cpus", "2", "--out-dir", str(out), "--run-name", "rg4", "--verbose", "0"])
    assert rc == 0
    return out / "rg4"


@needs_ray
@pytest.mark.slow
def test_one_ppo_iteration_on_random_goals_behind_the_filter(trained_run):
    run = trained_run
    assert {p.name for p in run.iterdir()} == {"config.json", "policy.json", "progress.jsonl", "train_stats.json",
                                               "rl_module.npz", "checkpoints"}
    rows = [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["agent_steps"] == 1600 and rows[0]["iter_agent_steps"] == 1600
    assert np.isfinite(rows[0]["robot_return_mean"]) and np.isfinite(rows[0]["policy_loss"])
    spec = json.loads((run / "policy.json").read_text())
    assert spec["backend"] == "rllib" and spec["env"]["num_robots"] == 4 and spec["filter"] is not None
    ckpt = run / "checkpoints" / "iter_000001"
    assert (ckpt / "rl_module.npz").is_file() and (ckpt / "learner_group").is_dir()
    stats = json.loads((run / "train_stats.json").read_text())
    assert stats["agent_steps"] == 1600 and stats["final_checkpoint"] == "checkpoints/iter_000001"
    assert stats["agent_steps_this_run"] == 1600 and stats["resumed_from"] is None


@needs_ray
@pytest.mark.slow
def test_resume_continues_a_run_into_a_new_folder(trained_run, capsys):
    out = trained_run.parent
    rc = cli.main(["train", "--backend", "rllib", "--config", str(trained_run / "config.json"), "--resume",
                   str(trained_run), "--iterations", "1", "--verbose", "0"])
    assert rc == 0
    run = out / "rg4_2"  # the same run name: a new folder, the old one untouched
    rows = [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]
    assert rows[0]["iteration"] == 2 and rows[0]["agent_steps"] == 3200  # counters continue from the checkpoint
    stats = json.loads((run / "train_stats.json").read_text())
    assert stats["final_checkpoint"] == "checkpoints/iter_000002" and stats["agent_steps_this_run"] == 1600
    assert stats["resumed_from"].endswith("iter_000001")
    assert sorted(p.name for p in (trained_run / "checkpoints").iterdir()) == ["iter_000001"]


@needs_ray
@pytest.mark.slow
def test_rllib_agent_acts_like_rllibs_own_restore(trained_run):
    from agents.learned import load_learned
    from agents.rllib_agent import RLlibAgent

    agent = load_learned(trained_run)  # recognised by the run's policy.json
    assert isinstance(agent, RLlibAgent)
    restored = RLlibAgent.from_checkpoint(trained_run / "checkpoints" / "iter_000001")  # RLlib's (pickled) restore
    from_ckpt = RLlibAgent.load(trained_run / "checkpoints" / "iter_000001")
    env = agent.make_env()
    obs, _ = env.reset(seed=5)
    agent.reset(env)
    batch = np.stack([obs[a] for a in env.agents])
    actions = agent(batch)
    assert actions.shape == (4, 2) and actions.dtype == np.float32 and np.all(np.abs(actions) <= 1.0)
    assert np.array_equal(actions, restored(batch)) and np.array_equal(actions, from_ckpt(batch))
    assert np.array_equal(actions, agent(batch))  # deterministic
    steps = 0
    while env.agents and steps < 5:
        obs, *_ = env.step(agent.act(obs, env))
        steps += 1
    assert steps == 5


@needs_ray
@pytest.mark.slow
def test_rllib_agent_rejects_broken_files(trained_run, tmp_path):
    from agents.rllib_agent import RLlibAgent

    run = tmp_path / "run"
    shutil.copytree(trained_run, run, ignore=shutil.ignore_patterns("checkpoints"))
    weights = dict(np.load(run / "rl_module.npz"))
    weights.pop(next(k for k in sorted(weights) if k.endswith("weight")))
    np.savez(run / "rl_module.npz", **weights)
    with pytest.raises(DataFileError, match=r"got arrays .*, expected"):
        RLlibAgent.load(run)
    good = dict(np.load(trained_run / "rl_module.npz"))
    key = next(k for k in good if k.endswith("weight"))
    for change, match in (({key: np.full_like(good[key], np.nan)}, f"'{key}' holds non-finite values"),
                          ({key: good[key].T}, f"'{key}' has shape"),
                          ({"__class__": np.zeros(1)}, r"got arrays .*'__class__'")):
        np.savez(run / "rl_module.npz", **{**good, **change})
        with pytest.raises(DataFileError, match=match):
            RLlibAgent.load(run)
    np.savez(run / "rl_module.npz", **good)
    spec = json.loads((run / "policy.json").read_text())
    (run / "policy.json").write_text(json.dumps({**spec, "env": {**spec["env"], "action_mode": "wheel"}}))
    with pytest.raises(DataFileError, match=r"differs from the settings its weights were trained with"):
        RLlibAgent.load(run)
    (run / "policy.json").write_text(json.dumps(spec))
    (run / "rl_module.npz").write_bytes(b"not a zip")
    with pytest.raises(DataFileError, match="not a readable .npz file"):
        RLlibAgent.load(run)
    (run / "rl_module.npz").unlink()
    with pytest.raises(DataFileError, match="missing"):
        RLlibAgent.load(run)
    with pytest.raises(DataFileError, match="no policy.json"):
        RLlibAgent.load(tmp_path / "nowhere")


@needs_ray
@pytest.mark.slow
def test_aasoatt_evaluate_table_with_an_rllib_run(trained_run, tmp_path, capsys):
    out = tmp_path / "eval.md"
    rc = cli.main(["evaluate", "--filtered", str(trained_run), "--episodes", "1", "-q", "--out", str(out),
                   "--rows", "tracking + filter", "learned (filter)", "learned (filter) + filter"])
    assert rc == 0
    rows = {r["name"]: r for r in json.loads(out.with_suffix(".json").read_text())}
    assert set(rows) == {"tracking + filter", "learned (filter)", "learned (filter) + filter"}
    assert rows["learned (filter) + filter"]["collisions"] == 0
    assert rows["learned (filter) + filter"]["intervention_rate"] is not None
    assert "| learned (filter) + filter | 1 |" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------- README commands
def _commands(block: str) -> list[list[str]]:
    """The README block's command lines (comments dropped), console scripts from this venv."""
    cmds = []
    for line in block.splitlines():
        argv = shlex.split(line, comments=True)
        if not argv:
            continue
        if argv[0].startswith(".venv-rllib/bin/"):
            argv[0] = str(BIN / argv[0].removeprefix(".venv-rllib/bin/"))
        cmds.append(argv)
    return cmds


def _run(argv: list[str], cwd: Path, env: dict[str, str] | None = None, timeout: float = 300) -> str:
    proc = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{shlex.join(argv)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


@needs_ray
@pytest.mark.slow
def test_readme_rllib_local_commands(tmp_path):
    setup, train, evaluate = _commands(readme_block("rllib-local"))
    assert setup[:3] == ["python3", "-m", "venv"]  # run verbatim by .ci/run (test_ci_runs_the_readme_rllib_setup)
    assert train[1:4] == ["train", "--backend", "rllib"]
    _run(train + TINY + ["--num-cpus", "2"], cwd=tmp_path)
    (run,) = (tmp_path / "runs").iterdir()
    assert (run / "rl_module.npz").is_file()
    assert evaluate[1:3] == ["evaluate", "--filtered"] and evaluate[3] == f"runs/{run.name}"  # the run it made
    table = _run(evaluate + ["--episodes", "1", "-q"], cwd=tmp_path)
    assert "| learned (filter) + filter | 1 |" in table


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@needs_ray
@pytest.mark.slow
def test_readme_rllib_cluster_commands(tmp_path):
    """``ray start --head`` then the training with ``--address auto``, on a private one-node cluster.

    The cluster gets its own temp folder (``RAY_TMPDIR``, where ``--address auto`` looks) and free
    ports, so it neither sees nor disturbs other Ray instances on this machine; it is stopped by
    its process group.
    """
    start, train = _commands(readme_block("rllib-cluster"))
    assert start[1:3] == ["start", "--head"] and "--address" in train and train[train.index("--address") + 1] == "auto"
    ray_tmp = tempfile.mkdtemp(prefix="rc", dir="/tmp")  # short: Ray's socket paths must stay < 108 characters
    env = {**os.environ, "RAY_TMPDIR": ray_tmp}
    isolate = ["--port", str(_free_port()), "--dashboard-agent-listen-port", str(_free_port()),
               "--dashboard-agent-grpc-port", str(_free_port()), "--metrics-export-port", str(_free_port()),
               "--runtime-env-agent-port", str(_free_port()), "--num-cpus", "2", "--include-dashboard", "false",
               "--disable-usage-stats", "--block"]
    log = (tmp_path / "head.log").open("w")
    head = subprocess.Popen(start + isolate, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in (tmp_path / "head.log").read_text():
            assert head.poll() is None, (tmp_path / "head.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "ray start --head did not come up in 120 s"
            time.sleep(0.5)
        _run(train + TINY + ["--num-env-runners", "1"], cwd=tmp_path, env=env)
        (run,) = (tmp_path / "runs").iterdir()
        stats = json.loads((run / "train_stats.json").read_text())
        assert stats["ray_nodes"] == 1 and stats["num_env_runners"] == 1 and stats["agent_steps"] >= 1600
    finally:
        _stop_group(head)
        log.close()
        shutil.rmtree(ray_tmp, ignore_errors=True)


def _stop_group(head: subprocess.Popen) -> None:
    """SIGTERM the process group of our ``ray start`` (Ray drains up to 30 s), SIGKILL what is left after 5 s."""
    pgid = head.pid  # start_new_session: the group of the Ray processes this test started, and only those
    try:
        os.killpg(pgid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        head.poll()  # reap the leader once it exits
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.2)
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    head.wait(timeout=10)


def test_ci_runs_the_readme_rllib_setup():
    setup = readme_block("rllib-local").splitlines()[0]
    ci = (Path(__file__).resolve().parents[1] / ".ci" / "run").read_text().splitlines()
    assert setup in ci


@needs_ray
@pytest.mark.slow
def test_a_failed_rllib_run_leaves_no_folder(tmp_path, monkeypatch):
    """A run that fails before any checkpoint is removed (train.config.abandon_run), and Ray is shut down."""
    import ray

    import train.rllib as tr

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(tr, "_metrics", boom)  # fails right after the first iteration's algo.train()
    config = RLlibConfig(scenario="random_goals", num_robots=4, iterations=1, train_batch_size=400, minibatch_size=128,
                         num_epochs=2, num_cpus=2, out_dir=str(tmp_path), run_name="x", verbose=0)
    with pytest.raises(RuntimeError, match="boom"):
        tr.train(config)
    assert list(tmp_path.iterdir()) == [] and not ray.is_initialized()
