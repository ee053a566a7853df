"""Command-line inputs: learned runs bring their env settings, animation formats, required scenario
parameters, evaluation rows and model paths (one-line errors, exit status 2, before any work)."""

import json
import time
from pathlib import Path

import pytest
from helpers import tiny_train_config

import aasoatt_env.apps.cli as cli
from aasoatt_env.apps.cli import main
from aasoatt_env.sim.rendering import ANIMATION_SUFFIXES

SMALL = ["run", "--scenario", "circle_swap", "--robots", "2", "-p", "radius=1.0", "-p", "duration=0.5", "-q"]


def _cli(argv, capsys):
    """``(exit status, stdout, stderr lines)`` of ``aasoatt argv`` (argparse's SystemExit included)."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, [line for line in captured.err.splitlines() if line.strip()]


# --------------------------------------------------------------------------- 1: a learned run's env settings
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run of ``aasoatt train`` (a few hundred steps) whose env differs from the CLI's defaults."""
    pytest.importorskip("stable_baselines3")
    torch = pytest.importorskip("torch")

    from train.train import train

    torch.set_num_threads(1)
    cfg = tiny_train_config(tmp_path_factory.mktemp("runs"), scenario="random_goals", run_name="tiny",
                            decision_interval=5, action_mode="point", num_neighbors=2, num_obstacles=1)
    return train(cfg).parent


def test_run_learned_takes_the_runs_env_settings(tiny_run, tmp_path, monkeypatch, capsys):
    spec = json.loads((tiny_run / "policy.json").read_text())["env"]
    assert (spec["action_mode"], spec["decision_interval"], spec["num_neighbors"]) == ("point", 5, 2)
    seen = {}
    episode = cli.run_episode

    def spy(env, agent, **kw):
        base = env.unwrapped
        seen.update(action_mode=base.action_mode, decision_interval=base.decision_interval, dt=base.dt,
                    num_neighbors=base.num_neighbors, num_obstacles=base.num_obstacles)
        return episode(env, agent, **kw)

    monkeypatch.setattr(cli, "run_episode", spy)
    out = tmp_path / "out"
    argv = ["run", "--scenario", "random_goals", "--robots", "3", "-p", "max_steps=3", "--controller", "learned",
            "--model", str(tiny_run), "--filter", "none", "-q", "--out", str(out)]
    code, stdout, err = _cli(argv, capsys)
    assert code == 0, err
    assert seen == {"action_mode": "point", "decision_interval": 5, "dt": spec["dt"], "num_neighbors": 2,
                    "num_obstacles": 1}
    assert json.loads((out / "metrics.json").read_text())["n_robots"] == 3 and "rmse" in stdout
    # the same values given explicitly are fine
    seen.clear()
    code, _, err = _cli(argv[:-2] + ["--decision-interval", "5", "-p", "action_mode=point"], capsys)
    assert code == 0 and seen["decision_interval"] == 5, err


@pytest.mark.parametrize(("extra", "match"), [
    (["--decision-interval", "1"], "--decision-interval: got decision_interval=1, expected decision_interval=5"),
    (["-p", "action_mode=wheel"], "-p/--param: got action_mode='wheel', expected action_mode='point'"),
    (["-p", "num_neighbors=4"], "-p/--param: got num_neighbors=4, expected num_neighbors=2"),
])
def test_run_learned_refuses_conflicting_env_settings(tiny_run, capsys, no_work, extra, match):
    argv = ["run", "--scenario", "random_goals", "--robots", "3", "--controller", "learned", "--model",
            str(tiny_run), "-q", *extra]
    code, _, err = _cli(argv, capsys)
    assert code == 2 and len(err) == 1, err
    assert match in err[0] and "--model" in err[0] and "trained with" in err[0]


# --------------------------------------------------------------------------- 2: animation formats
@pytest.mark.parametrize("suffix", [".webm", ".m4v", ".mpg", ".txt"])
def test_gif_refuses_formats_without_a_working_writer(tmp_path, capsys, no_work, suffix):
    target = tmp_path / f"a{suffix}"
    code, _, err = _cli(SMALL + ["--gif", str(target)], capsys)
    assert code == 2 and len(err) == 1, err
    assert "--gif:" in err[0] and str(list(ANIMATION_SUFFIXES)) in err[0]
    assert not target.exists() and list(tmp_path.iterdir()) == []


def test_gif_refuses_a_video_without_imageio_ffmpeg(tmp_path, capsys, no_work, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg"
                        else real(name, *a))
    code, _, err = _cli(SMALL + ["--gif", str(tmp_path / "a.mp4")], capsys)
    assert code == 2 and len(err) == 1 and "but writing '.mp4' needs imageio-ffmpeg" in err[0]
    assert err[0].split("error: ", 1)[1].startswith("--gif: ")


@pytest.mark.parametrize("suffix", ANIMATION_SUFFIXES)
def test_every_accepted_animation_suffix_writes(tmp_path, suffix):
    if suffix != ".gif":
        pytest.importorskip("imageio_ffmpeg")
    target = tmp_path / f"a{suffix}"
    assert main(SMALL + ["--filter", "none", "--gif", str(target), "--frame-every", "20"]) == 0
    assert target.stat().st_size > 1000
    assert [p.name for p in tmp_path.iterdir()] == [target.name]  # no temporary file left


def test_failed_animation_leaves_no_file(tmp_path, capsys, monkeypatch):
    import aasoatt_env.sim.rendering as rendering

    def broken(iio, images, path, suffix, fps):
        Path(path).write_bytes(b"x" * 262)  # what a failing ffmpeg leaves behind
        raise RuntimeError("Broken pipe")

    monkeypatch.setattr(rendering, "_write_animation", broken)
    target = tmp_path / "a.mp4"
    code, _, err = _cli(SMALL + ["--filter", "none", "--gif", str(target)], capsys)
    assert code == 1 and len(err) == 1 and f"--gif: could not write {target}" in err[0] and "Broken pipe" in err[0]
    assert list(tmp_path.iterdir()) == []
    # an earlier file is kept when the new one fails
    target.write_bytes(b"earlier")
    code, _, err = _cli(SMALL + ["--filter", "none", "--gif", str(target), "--overwrite"], capsys)
    assert code == 1 and target.read_bytes() == b"earlier" and [p.name for p in tmp_path.iterdir()] == ["a.mp4"]


# --------------------------------------------------------------------------- 3: required scenario parameters
def test_custom_scenario_names_its_missing_parameters(capsys, no_work):
    t0 = time.perf_counter()
    code, _, err = _cli(["run", "--scenario", "custom", "-q"], capsys)
    assert code == 2 and len(err) == 1, err
    assert "--scenario custom: missing required parameter(s) starts, reference" in err[0]
    assert "-p starts=... -p reference=..." in err[0] and "Traceback" not in err[0]
    code, _, err = _cli(["run", "--scenario", "custom", "-p", "starts=[[0, 0]]", "-q"], capsys)
    assert code == 2 and "missing required parameter(s) reference;" in err[0]
    assert time.perf_counter() - t0 < 2.0


def test_required_parameters_of_every_scenario():
    from aasoatt_env.sim.scenarios import SCENARIOS

    required = {name: cli._required_parameters(name) for name in SCENARIOS}
    assert required.pop("custom") == ["starts", "reference"]
    assert all(not params for params in required.values()), required


# --------------------------------------------------------------------------- 4-6: evaluate rows and models
@pytest.mark.parametrize(("rows", "match"), [
    (["learned (bare)"], "--rows: got 'learned (bare)', which needs --bare"),
    (["learned (bare) + filter"], "--rows: got 'learned (bare) + filter', which needs --bare"),
    (["learned (filter) + filter", "random"], "--rows: got 'learned (filter) + filter', which needs --filtered"),
    (["random", "learned (filter)"], "--rows: got 'learned (filter)', which needs --filtered"),
])
def test_evaluate_refuses_rows_without_their_model(capsys, no_work, rows, match):
    code, out, err = _cli(["evaluate", "--episodes", "1", "--rows", *rows, "-q"], capsys)
    assert code == 2 and len(err) == 1 and match in err[0], err
    assert out == ""


def test_evaluate_api_refuses_rows_without_their_model(no_work):
    from aasoatt_env.errors import ConfigError
    from train.evaluate import evaluate

    with pytest.raises(ConfigError, match=r"rows: got 'learned \(bare\)', which needs bare_model"):
        evaluate(episodes=1, rows=["learned (bare)"])


def test_evaluate_rllib_run_without_ray_says_how_to_install(tmp_path, capsys, no_work, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    run = tmp_path / "rllib_run"
    run.mkdir()
    (run / "policy.json").write_text(json.dumps({"backend": "rllib", "env": {}, "policy": "DefaultPPOTorchRLModule",
                                                 "model_config": {}}))
    (run / "rl_module.npz").write_bytes(b"")
    for argv in (["evaluate", "--filtered", str(run), "--episodes", "1"],
                 ["run", "--controller", "learned", "--model", str(run), "-q"]):
        code, _, err = _cli(argv, capsys)
        assert code == 2 and len(err) == 1, err
        flag = "--filtered" if argv[0] == "evaluate" else "--model"
        assert f"{flag}: '{run}' is a Ray RLlib run; Ray RLlib is not installed" in err[0]
        assert ".venv-rllib/bin/pip install -e" in err[0] and "Traceback" not in err[0]


@pytest.mark.parametrize("what", ["passwd", "folder", "missing"])
def test_evaluate_names_the_model_path_given(tmp_path, capsys, no_work, what):
    path = {"passwd": tmp_path / "etc" / "passwd", "folder": tmp_path / "etc", "missing": tmp_path / "nope"}[what]
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "passwd").write_text("root:x:0:0\n")
    for argv, flag in ((["evaluate", "--bare", str(path), "--episodes", "1"], "--bare"),
                       (["evaluate", "--filtered", str(path), "--episodes", "1"], "--filtered"),
                       (["run", "--controller", "learned", "--model", str(path), "-q"], "--model")):
        code, _, err = _cli(argv, capsys)
        assert code == 2 and len(err) == 1, err
        assert err[0].split("error: ", 1)[1].startswith(f"{flag}: ") and repr(str(path)) in err[0]
        assert "expected a run folder" in err[0] and "policy.json" in err[0]
        assert "etc/policy.json" not in err[0]


def test_evaluate_refuses_a_config_the_policy_was_not_trained_for(tiny_run, tmp_path, capsys, no_work):
    cfg = tmp_path / "env.toml"
    cfg.write_text('scenario = "random_goals"\nnum_robots = 3\ndecision_interval = 1\n')
    code, _, err = _cli(["evaluate", "--bare", str(tiny_run), "--config", str(cfg), "--episodes", "1"], capsys)
    assert code == 2 and len(err) == 1, err
    assert "--config: got decision_interval=1, expected decision_interval=5" in err[0] and "--bare" in err[0]
