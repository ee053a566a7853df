"""Bad input to training, fine-tuning, the comparison and the RLlib loader: one clear error, before anything runs."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import tiny_train_config

from aasoatt_env.errors import ConfigError, DataFileError


def _tiny(out: Path, **kw):
    return tiny_train_config(out, **{"total_timesteps": 96, "net_arch": [8], **kw})


_TINY_ARGS = ["--num-robots", "3", "--n-envs", "2", "--n-steps", "16", "--batch-size", "48", "--n-epochs", "1",
              "--total-timesteps", "96", "--net-arch", "8", "--progress-bar", "false", "--tensorboard", "false",
              "--checkpoint-freq", "0", "--max-steps", "20"]


@pytest.fixture(scope="module")
def src_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished tiny run (point actions, 4 neighbours) to fine-tune from."""
    pytest.importorskip("stable_baselines3")
    torch = pytest.importorskip("torch")
    from train.train import train

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("src")
    return train(_tiny(out, run_name="src")).parent


def _folders(path: Path) -> list[str]:
    return sorted(p.name for p in path.iterdir()) if path.is_dir() else []


# ------------------------------------------------------------------------------------ defect 1: --device, folders
@pytest.mark.parametrize("device", ["banana", "cuda:9", "cpu:1", ""])
def test_unavailable_device_is_refused_naming_the_devices_there(device):
    torch = pytest.importorskip("torch")
    from train.train import check_device

    if device == "cuda:9" and torch.cuda.device_count() > 9:
        pytest.skip("this machine has a cuda:9")
    with pytest.raises(ConfigError, match=rf"TrainConfig.device \(--device\): got '{device}', expected a torch "
                                          r"device available here, one of \['auto', 'cpu'"):
        check_device(device)
    check_device("cpu")
    check_device("auto")


def test_cli_bad_device_is_one_line_status_2_and_leaves_no_folder(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    from train.train import main

    out = tmp_path / "runs"
    assert main(["--device", "banana", "--out-dir", str(out), *_TINY_ARGS]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--device" in err and "'banana'" in err and "Traceback" not in err
    assert _folders(out) == []


def test_a_failed_training_leaves_no_folder_that_looks_finished(tmp_path, monkeypatch):
    pytest.importorskip("stable_baselines3")
    import train.train as tt

    def crash(*args):
        raise RuntimeError("boom")

    monkeypatch.setattr(tt, "_learn", crash)
    with pytest.raises(RuntimeError, match="boom"):
        tt.train(_tiny(tmp_path, run_name="r"))
    assert _folders(tmp_path) == []  # nothing of value: removed

    def crash_after_a_checkpoint(config, run, *args):
        (run / "checkpoints").mkdir()
        (run / "checkpoints" / "ppo_96_steps.zip").write_bytes(b"weights")
        raise KeyboardInterrupt

    monkeypatch.setattr(tt, "_learn", crash_after_a_checkpoint)
    with pytest.raises(KeyboardInterrupt):
        tt.train(_tiny(tmp_path, run_name="r"))
    run = tmp_path / "r"
    assert (run / tt.INCOMPLETE_FILE).is_file() and (run / "checkpoints" / "ppo_96_steps.zip").is_file()
    assert not (run / "train_stats.json").exists()


def test_a_failed_training_keeps_a_folder_it_was_given(tmp_path, monkeypatch):
    """An empty folder (or a link to one) that existed before the run is emptied, not deleted."""
    pytest.importorskip("stable_baselines3")
    import train.train as tt

    def crash(*args):
        raise RuntimeError("boom")

    monkeypatch.setattr(tt, "_learn", crash)
    (tmp_path / "mine").mkdir()
    with pytest.raises(RuntimeError, match="boom"):
        tt.train(_tiny(tmp_path, run_name="mine"))
    assert (tmp_path / "mine").is_dir() and list((tmp_path / "mine").iterdir()) == []
    (tmp_path / "target").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "target")
    with pytest.raises(RuntimeError, match="boom"):
        tt.train(_tiny(tmp_path, run_name="link"))
    assert (tmp_path / "link").is_symlink() and list((tmp_path / "target").iterdir()) == []


def test_two_runs_never_claim_one_folder(tmp_path):
    from train.config import INCOMPLETE_FILE, claim_run_dir

    (tmp_path / "r").mkdir()  # an empty folder: the first claim takes it, the second moves on
    a, made_a = claim_run_dir(tmp_path, "r")
    b, made_b = claim_run_dir(tmp_path, "r")
    assert (a.name, made_a, b.name, made_b) == ("r", False, "r_2", True)
    assert (a / INCOMPLETE_FILE).is_file() and (b / INCOMPLETE_FILE).is_file()


def test_a_run_folder_under_a_dangling_link_is_an_error_not_a_hang(tmp_path):
    from train.config import claim_run_dir

    (tmp_path / "out").symlink_to(tmp_path / "nowhere")
    with pytest.raises(FileExistsError):
        claim_run_dir(tmp_path / "out", "r")


def test_a_finished_run_has_no_incomplete_marker(src_run):
    from train.train import INCOMPLETE_FILE

    assert (src_run / "train_stats.json").is_file() and not (src_run / INCOMPLETE_FILE).exists()


# ------------------------------------------------------------------------------------ defect 2: --init-from
@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"action_mode": "wheel"}, r"action_mode: got 'wheel', the init_from run has 'point'"),
        ({"num_neighbors": 2}, r"num_neighbors: got 2, the init_from run has 4"),
        ({"num_obstacles": 1}, r"num_obstacles: got 1, the init_from run has 2"),
        ({"decision_interval": 10}, r"decision_interval: got 10, the init_from run has 20"),
        ({"net_arch": [16]}, r"net_arch: got \[16\], the init_from run has \[8\]"),
        ({"normalize_obs": False}, r"normalize_obs: got False, the init_from run has True"),
    ],
)
def test_init_from_with_settings_the_policy_depends_on_changed_is_refused_before_any_folder(
        src_run, tmp_path, kw, match):
    from train.train import train

    with pytest.raises(ConfigError, match=rf"TrainConfig.init_from: .*src was trained with other settings .*{match}"):
        train(_tiny(tmp_path, init_from=str(src_run), **kw))
    assert _folders(tmp_path) == []


def test_init_from_names_every_differing_setting(src_run, tmp_path):
    from agents.learned import LearnedAgent
    from train.train import check_init_from

    cfg = _tiny(tmp_path, init_from=str(src_run), action_mode="wheel", num_neighbors=2)
    with pytest.raises(ConfigError, match=r"action_mode: got 'wheel', the init_from run has 'point'; "
                                          r"num_neighbors: got 2, the init_from run has 4\)"):
        check_init_from(cfg, LearnedAgent.load(src_run))
    check_init_from(_tiny(tmp_path, init_from=str(src_run), filter=True), LearnedAgent.load(src_run))  # fits


def test_cli_init_from_mismatch_is_status_2_without_a_folder(src_run, tmp_path, capsys):
    from train.train import main

    out = tmp_path / "runs"
    assert main(["--init-from", str(src_run), "--num-neighbors", "2", "--out-dir", str(out), *_TINY_ARGS]) == 2
    assert "num_neighbors: got 2, the init_from run has 4" in capsys.readouterr().err
    assert _folders(out) == []


# ------------------------------------------------------------------------------------ defect 3: train.compare
@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--correction", "nan", "--seeds", "-1", "--table-only"], r"--correction: got nan, expected a finite number"),
        (["--seeds", "-1", "--table-only"], r"--seeds: got -1, expected an integer >= 0"),
        (["--correction", "inf"], r"--correction: got inf, expected a finite number >= 0"),
        (["--correction", "-0.5"], r"--correction: got -0.5, expected a finite number >= 0"),
        (["--seeds", "0", "0"], r"--seeds: got 0 more than once"),
        (["--bare-steps", "0"], r"--bare-steps: got 0, expected an integer >= 1"),
        (["--episodes", "-3"], r"--episodes: got -3, expected an integer >= 1"),
        (["--seeds", "0", "--table-only"], r"--table-only: .* holds no finished, evaluated run"),
    ],
)
def test_compare_options_are_checked_before_anything_runs_or_is_written(tmp_path, capsys, monkeypatch, argv, match):
    import train.compare as tc

    monkeypatch.setattr(tc, "_train", lambda *a: pytest.fail("trained despite a bad option"))
    out = tmp_path / "cmp"
    try:
        rc = tc.main(["--out-dir", str(out), *argv])
    except SystemExit as exc:  # argparse's own option types exit with status 2
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert _folders(out) == []


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"correction": math.nan}, r"--correction: got nan"),
        ({"seeds": [-1]}, r"--seeds: got \[-1\], expected one or more integers >= 0"),
        ({"seeds": [0.5]}, r"--seeds: got \[0.5\]"),
        ({"filter_steps": 0}, r"--filter-steps: got 0"),
        ({"episodes": 0}, r"--episodes: got 0"),
        ({"scenes": ["nowhere"]}, r"--scenes: got \['nowhere'\]"),
    ],
)
def test_run_comparison_checks_its_arguments_before_training(tmp_path, monkeypatch, kw, match):
    import train.compare as tc

    monkeypatch.setattr(tc, "_train", lambda *a: pytest.fail("trained despite a bad argument"))
    with pytest.raises(ConfigError, match=match):
        tc.run_comparison(tmp_path / "cmp", **{"scenes": ["random_goals_6r"], "seeds": [0], **kw})
    assert _folders(tmp_path / "cmp") == []


def test_compare_json_never_holds_a_bare_nan(tmp_path):
    from train.runs import write_json as _write_json

    path = tmp_path / "x.json"
    _write_json(path, {"a": math.nan, "b": [np.float32("inf"), 1.5, np.int64(3)], "c": {"d": -math.inf}})

    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    assert json.loads(path.read_text(), parse_constant=refuse) == {"a": None, "b": [None, 1.5, 3], "c": {"d": None}}


# ------------------------------------------------------------------------------------ defect 4: RLlib model_config
def _rllib_run(tmp_path: Path, model_config: dict) -> Path:
    run = tmp_path / "rllib_run"
    run.mkdir()
    spec = {"format": 1, "backend": "rllib", "env": {"scenario": "random_goals", "num_robots": 3},
            "filter": None, "policy": "DefaultPPOTorchRLModule", "model_config": model_config, "normalize_obs": False}
    (run / "policy.json").write_text(json.dumps(spec))
    np.savez(run / "rl_module.npz", w=np.zeros(1))
    return run


@pytest.mark.parametrize(
    ("model_config", "match"),
    [
        ({"fcnet_hiddens": [10**9], "fcnet_activation": "tanh", "vf_share_layers": False},
         r"model_config.fcnet_hiddens: got \[1000000000\], expected a list of at most 16 layer sizes in \[1, 4096\]"),
        ({"fcnet_hiddens": [64] * 17}, r"fcnet_hiddens: got .*, expected a list of at most 16 layer sizes"),
        ({"fcnet_hiddens": {"pi": [64]}}, r"fcnet_hiddens: got \{'pi': \[64\]\}, expected a list"),
        ({"fcnet_hiddens": [64], "head_fcnet_hiddens": [10**9]},
         r"model_config: unexpected keys \['head_fcnet_hiddens'\]"),
        ({"fcnet_hiddens": [64], "fcnet_activation": "os.system"}, r"fcnet_activation: got 'os.system'"),
        ({"fcnet_hiddens": [64], "vf_share_layers": "yes"}, r"vf_share_layers: got 'yes', expected true or false"),
    ],
)
def test_rllib_loader_bounds_model_config_before_importing_ray(tmp_path, model_config, match):
    import sys

    from agents.rllib_agent import RLlibAgent

    had_ray = "ray" in sys.modules
    with pytest.raises(DataFileError, match=match):
        RLlibAgent.load(_rllib_run(tmp_path, model_config))
    assert had_ray or "ray" not in sys.modules  # refused before Ray was imported
