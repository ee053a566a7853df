"""Runs a researcher can trust: atomic files, resumed runs, held-out evaluation, intervals, several seeds."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import tiny_train_config

from train.intervals import spread, wilson
from train.runs import atomic_write, save_npz, write_json

torch = pytest.importorskip("torch")
pytest.importorskip("stable_baselines3")

ROLLOUT = 96  # agent-steps of one rollout of the tiny runs: 16 decisions x 2 teams x 3 robots
TINY = ["--num-robots", "3", "--n-envs", "2", "--n-steps", "16", "--batch-size", "48", "--n-epochs", "1",
        "--net-arch", "8", "--progress-bar", "false", "--tensorboard", "false", "--checkpoint-freq", "0",
        "--max-steps", "20", "--eval-every", str(ROLLOUT), "--eval-episodes", "2"]


def _tiny(out: Path, **kw: object):
    return tiny_train_config(out, **{"total_timesteps": 2 * ROLLOUT, "eval_every": ROLLOUT, "eval_episodes": 2,
                                     **kw})


# --------------------------------------------------------------------------------------- atomic writes
def test_a_writer_that_fails_half_way_leaves_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "normalization.npz"
    save_npz(target, mean=np.ones(3))
    before = target.read_bytes()

    def half(fh, **arrays):
        fh.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", half)
    with pytest.raises(KeyboardInterrupt):
        save_npz(target, mean=np.zeros(3))
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["normalization.npz"]  # no temporary file left

    def fails(fh):
        fh.write(b'{"half": ')
        raise ValueError("disk full")

    with pytest.raises(ValueError, match="disk full"):
        atomic_write(tmp_path / "new.json", fails)
    assert [p.name for p in tmp_path.iterdir()] == ["normalization.npz"]
    write_json(tmp_path / "new.json", {"a": math.nan})
    assert json.loads((tmp_path / "new.json").read_text()) == {"a": None}  # strict JSON, never a bare NaN


_WRITER = """
import signal, sys
from train.runs import atomic_write

signal.signal(signal.SIGINT, signal.default_int_handler)  # (a runner started in the background ignores SIGINT)

def write(fh):
    print("writing", flush=True)
    for _ in range(100_000):
        fh.write(b"x" * 65536)

atomic_write(sys.argv[1], write)
"""


def test_ctrl_c_while_writing_leaves_no_partial_file(tmp_path):
    target = tmp_path / "rollout.npz"
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(target)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline() == "writing\n"
    deadline = time.monotonic() + 30
    while not any(p.name.startswith(".rollout.npz.") for p in tmp_path.iterdir()):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) != 0
    assert list(tmp_path.iterdir()) == []  # neither the target nor the temporary file


def test_an_interrupted_model_save_leaves_no_model(tmp_path, monkeypatch):
    from stable_baselines3 import PPO

    from train.train import train

    def half(self, path, *a, **k):
        Path(path).write_bytes(b"PK\x03\x04 half a model")
        raise KeyboardInterrupt

    monkeypatch.setattr(PPO, "save", half)
    with pytest.raises(KeyboardInterrupt):
        train(_tiny(tmp_path, run_name="r", eval_every=0))
    assert list(tmp_path.iterdir()) == []  # nothing of value: the run folder is removed, no partial model.zip


# --------------------------------------------------------------------------------------- resume
def _adam_steps(model_zip: Path) -> float:
    import zipfile

    from agents.run_files import load_tensor_file

    with zipfile.ZipFile(model_zip) as z:
        state = load_tensor_file(z.read("policy.optimizer.pth"), "x")
    return float(next(iter(state["state"].values()))["step"])


def test_resume_continues_the_curve_the_optimiser_and_the_statistics(tmp_path, capsys):
    from agents.learned import read_stats
    from train.telemetry import read_metrics
    from train.train import main, train

    first = train(_tiny(tmp_path, run_name="r")).parent
    assert main(["--resume", str(first), "--total-timesteps", str(4 * ROLLOUT)]) == 0
    resumed = tmp_path / "r_2"  # a new folder: the first run is untouched
    rows = read_metrics(resumed / "metrics.csv")
    assert [r["agent_steps"] for r in rows] == [ROLLOUT, 2 * ROLLOUT, 3 * ROLLOUT, 4 * ROLLOUT]
    assert json.dumps(rows[:2]) == json.dumps(read_metrics(first / "metrics.csv"))  # the earlier curve, continued
    walls = [r["wall_time_s"] for r in rows]
    assert walls == sorted(walls)
    evals = read_metrics(resumed / "eval.csv")
    assert [r["agent_steps"] for r in evals] == [ROLLOUT, 2 * ROLLOUT, 3 * ROLLOUT, 4 * ROLLOUT]
    stats = json.loads((resumed / "train_stats.json").read_text())
    assert (stats["agent_steps"], stats["agent_steps_this_run"]) == (4 * ROLLOUT, 2 * ROLLOUT)
    assert stats["resumed_from"] == str(first)
    # Adam continues: 2 minibatches per rollout, one epoch
    assert (_adam_steps(first / "model.zip"), _adam_steps(resumed / "model.zip")) == (4.0, 8.0)
    count = [float(read_stats(r / "normalization.npz", 50)["count"]) for r in (first, resumed)]
    assert count[1] == pytest.approx(count[0] + 2 * ROLLOUT + 6)  # continued (+ the 6 slots' first observations)
    assert "resuming" not in capsys.readouterr().err


def test_resume_starts_from_the_runs_exact_state(tmp_path):
    from agents.learned import LearnedAgent, read_stats
    from agents.sb3_model import read_optimizer_state
    from train.build import build_model, make_vec_env
    from train.resume import load_resumed, resume_into
    from train.train import train

    first = train(_tiny(tmp_path, run_name="r")).parent
    cfg = _tiny(tmp_path, resume=str(first), total_timesteps=4 * ROLLOUT)
    venv = make_vec_env(cfg)
    model = build_model(cfg, venv)
    resumed = load_resumed(cfg, tuple(venv.observation_space.shape))
    resume_into(model, venv, cfg, resumed)
    source = LearnedAgent.load(first)
    for k, v in source.model.policy.state_dict().items():
        assert torch.equal(v, model.policy.state_dict()[k]), k
    want = read_optimizer_state(first / "model.zip", model.policy.optimizer)["state"]
    got = model.policy.optimizer.state_dict()["state"]
    assert all(torch.equal(want[i][k], got[i][k]) for i in want for k in want[i])
    assert model.num_timesteps == 2 * ROLLOUT
    np.testing.assert_array_equal(venv.obs_rms.mean, read_stats(first / "normalization.npz", 50)["mean"])
    venv.close()


def test_an_interrupted_run_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    import train.train as tt
    from train.telemetry import read_metrics

    def crash(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(tt, "_finish", crash)
    with pytest.raises(KeyboardInterrupt):
        tt.train(_tiny(tmp_path, run_name="r", checkpoint_freq=ROLLOUT))
    run = tmp_path / "r"
    assert (run / tt.INCOMPLETE_FILE).is_file() and (run / "checkpoints" / f"ppo_{2 * ROLLOUT}_steps.zip").is_file()
    monkeypatch.undo()
    assert tt.main(["--resume", str(run), "--total-timesteps", str(3 * ROLLOUT)]) == 0
    rows = read_metrics(tmp_path / "r_2" / "metrics.csv")
    assert [r["agent_steps"] for r in rows] == [ROLLOUT, 2 * ROLLOUT, 3 * ROLLOUT]


@pytest.mark.parametrize(("argv", "match"), [
    (["--total-timesteps", str(2 * ROLLOUT)], r"TrainConfig.total_timesteps: got 192, but .* has already trained 192"),
    (["--num-neighbors", "2"], r"TrainConfig.resume: .*num_neighbors: got 2, the resume run has 4"),
    (["--net-arch", "16"], r"net_arch: got \[16\], the resume run has \[8, 8\]"),
])
def test_resume_refuses_what_does_not_continue_the_run(tmp_path, capsys, argv, match):
    import re

    from train.train import main, train

    first = train(_tiny(tmp_path, run_name="r")).parent
    assert main(["--resume", str(first), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


# --------------------------------------------------------------------------------------- held-out evaluation
def test_held_out_evaluation_runs_on_seeds_never_used_for_training(tmp_path, monkeypatch):
    import train.evaluate as tev
    from aasoatt_env.sim.batched import BatchedAASOATTEnv
    from train.config import HELDOUT_SEED
    from train.telemetry import read_metrics
    from train.train import train

    eval_seeds: list[int] = []
    reset_seeds: list[object] = []
    evaluate_agent, reset = tev.evaluate_agent, BatchedAASOATTEnv.reset

    def spy_eval(name, agent, env_fn, episodes, seed, *a, **k):
        eval_seeds.extend(range(seed, seed + episodes))
        return evaluate_agent(name, agent, env_fn, episodes, seed, *a, **k)

    def spy_reset(self, seed=None, options=None):
        reset_seeds.append(seed)
        return reset(self, seed=seed, options=options)

    monkeypatch.setattr(tev, "evaluate_agent", spy_eval)
    monkeypatch.setattr(BatchedAASOATTEnv, "reset", spy_reset)
    run = train(_tiny(tmp_path, run_name="r", seed=2**31 - 1)).parent
    rows = read_metrics(run / "eval.csv")
    assert [r["agent_steps"] for r in rows] == [ROLLOUT, 2 * ROLLOUT]
    assert all(0 <= r["success_rate_lo"] <= r["success_rate"] <= r["success_rate_hi"] <= 1 for r in rows)
    assert eval_seeds == [HELDOUT_SEED, HELDOUT_SEED + 1] * 2
    training = [s for seeds in reset_seeds if seeds is not None for s in seeds if s is not None]
    assert training and max(training) < HELDOUT_SEED  # disjoint: training resets stay below 2**32
    stats = json.loads((run / "train_stats.json").read_text())
    assert stats["last_heldout"]["agent_steps"] == 2 * ROLLOUT


# --------------------------------------------------------------------------------------- intervals, seeds
def test_wilson_intervals():
    lo, hi = wilson(100, 100)
    assert (round(lo, 4), hi) == (0.963, 1.0)
    lo, hi = wilson(0, 100)
    assert (lo, round(hi, 4)) == (0.0, 0.037)
    lo, hi = wilson(50, 100)
    assert (round(lo, 4), round(hi, 4)) == (0.4038, 0.5962)
    assert all(math.isnan(x) for x in wilson(0, 0))
    s = spread([0.9, 1.0, 0.95])
    assert (round(s["mean"], 9), round(s["std"], 9), s["min"], s["max"], s["n"]) == (0.95, 0.05, 0.9, 1.0, 3)


def test_evaluate_reports_95_percent_intervals(tmp_path, capsys):
    from aasoatt_env.apps.cli import main

    assert main(["evaluate", "--rows", "random", "tracking", "--episodes", "3", "-q", "--out",
                 str(tmp_path / "t.md")]) == 0
    out = capsys.readouterr().out
    assert "success [95% CI]" in out and "episodes with a collision [95% CI]" in out
    page = (tmp_path / "t.md").read_text()  # the table, headed by the command that made it
    assert page.startswith("```bash\naasoatt evaluate --rows random tracking --episodes 3 -q --out ")
    table = page.split("```\n\n", 1)[1].strip()
    assert table.startswith("| agent |") and table in out  # the table printed
    rows = {r["name"]: r for r in json.loads((tmp_path / "t.json").read_text())}
    r = rows["tracking"]
    assert r["robot_episodes"] == 3 * 6  # 3 episodes of the default task's 6 robots
    assert r["success_ci"][0] <= r["success_rate"] <= r["success_ci"][1]
    k = round(r["success_rate"] * r["robot_episodes"])
    assert r["success_ci"] == list(wilson(k, r["robot_episodes"]))
    assert r["collision_episode_ci"] == list(wilson(r["collision_episodes"], 3))


def test_several_seeds_report_mean_and_spread(tmp_path, capsys):
    from train.train import main

    assert main(["--seeds", "0", "1", "--out-dir", str(tmp_path), "--run-name", "g", "--total-timesteps",
                 str(ROLLOUT), *TINY]) == 0
    group = tmp_path / "g"
    assert {p.name for p in group.iterdir()} >= {"s0", "s1", "seeds.json", "seeds.md"}
    data = json.loads((group / "seeds.json").read_text())
    finals = [json.loads((group / s / "train_stats.json").read_text())["last_heldout"] for s in ("s0", "s1")]
    mean = (finals[0]["success_rate"] + finals[1]["success_rate"]) / 2
    assert data["summary"]["success_rate"]["mean"] == pytest.approx(mean)
    assert data["summary"]["success_rate"]["n"] == 2
    assert "| success_rate |" in capsys.readouterr().out
    assert not (group / "INCOMPLETE").exists()


@pytest.mark.parametrize(("argv", "match"), [
    (["--seeds", "0", "0"], r"--seeds: got \[0\] more than once"),
    (["--seeds", "0", "--seed", "3"], r"--seeds: got \[0\] with --seed 3, expected one of them"),
    (["--seeds", "-1"], r"--seeds: got \[-1\], expected 1 to 100 integers"),
    (["--seeds", "0", "--eval-every", "0"], r"--seeds: needs held-out evaluations"),
])
def test_bad_seeds_are_refused_before_anything(tmp_path, capsys, argv, match):
    import re

    from train.train import main

    assert main([*argv, "--out-dir", str(tmp_path / "o"), *TINY[:-4]]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert not (tmp_path / "o").exists()


def test_no_temporary_files_are_left_in_a_run(tmp_path):
    from train.train import train

    run = train(_tiny(tmp_path, run_name="r", checkpoint_freq=ROLLOUT)).parent
    leftovers = [p for p in run.rglob("*") if ".tmp" in p.name]
    assert leftovers == [] and os.listdir(run)


def test_training_that_diverges_names_the_hyper_parameters(tmp_path, capsys):
    from train.train import main

    out = tmp_path / "runs"
    assert main(["--out-dir", str(out), *TINY, "--n-epochs", "10", "--total-timesteps", "2000", "--learning-rate",
                 "1.0", "--max-grad-norm", "1000", "--vf-coef", "100", "--ent-coef", "10", "--eval-every", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "TrainConfig: training diverged at" in err and "learning_rate=1," in err
    assert list(out.iterdir()) == []  # nothing of value: the run folder is removed
