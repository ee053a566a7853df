import json

import pytest

from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.apps.cli import main


def test_list_shows_scenarios_controllers_and_filter_options(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for word in (
        "circle_swap",
        "aasoatt/CircleSwap-v0",
        "random_goals",
        "custom",
        "tracking",
        "hostile",
        "braking",
        "auxiliary_velocity",
        "multiplier",
        "proxsuite",
        "neural",
    ):
        assert word in out


SMALL_SWAP = ["run", "--scenario", "circle_swap", "--robots", "4", "-p", "radius=2.0", "-p", "duration=3.0", "-q"]


def test_run_writes_metrics_rollout_plot_and_gif(tmp_path, capsys):
    gif = tmp_path / "swap.gif"
    out = tmp_path / "run"
    extra = ["--gif", str(gif), "--frame-every", "100", "--out", str(out), "--fail-on-collision"]
    assert main(SMALL_SWAP + extra) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_collision_pairs"] == 0 and metrics["reach_rate"] == 1.0
    assert metrics["min_center_distance"] >= 0.96 - 1e-3
    rollout = Rollout.load(out / "rollout.npz")
    assert rollout.positions.shape[1] == 4 and rollout.avoiding is not None
    assert (out / "trajectories.png").stat().st_size > 1000
    assert gif.stat().st_size > 1000
    assert "rmse" in capsys.readouterr().out


def test_bare_run_collides_and_fail_flag_reports_it():
    assert main(SMALL_SWAP + ["--filter", "none", "--fail-on-collision"]) == 1


def test_run_unknown_scenario_lists_known(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "--scenario", "donut", "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'donut'" in err and "circle_swap" in err and len(err.strip().splitlines()) == 1


def test_forwarded_help_exits_cleanly():
    with pytest.raises(SystemExit) as exc:
        main(["train", "--help"])
    assert exc.value.code == 0
