import json
import time
from pathlib import Path

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
    assert "(default: 20 robots, FIG5_OBSTACLES), as CircleSwap." in out  # docstrings as plain text
    assert ":data:" not in out and "``" not in out


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


# --------------------------------------------------------------------------- bad options and output paths


def _cli(argv, capsys):
    """``(exit status, stderr lines, seconds)`` of ``aasoatt argv`` (argparse's SystemExit included)."""
    t0 = time.perf_counter()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    seconds = time.perf_counter() - t0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return code, err, seconds


def _bad_cases(tmp: Path) -> list[tuple[list[str], str]]:
    (tmp / "a_file").write_text("x")
    (tmp / "done").mkdir()
    (tmp / "done" / "metrics.json").write_text("{}")
    (tmp / "table.md").write_text("| earlier |")
    return [
        (["run", "--out", "/proc/x"], "--out: cannot write to /proc/x"),
        (["run", "--out", "/dev/null"], "--out: /dev/null exists and is not a folder"),
        (["run", "--out", str(tmp / "a_file")], "exists and is not a folder"),
        (["run", "--out", str(tmp / "done")], "already holds results (metrics.json); pass --overwrite"),
        (["run", "--gif", "/proc/x/a.gif"], "--gif: cannot write"),
        (["run", "--gif", str(tmp / "a.txt")], "--gif: got"),
        (["run", "--fps", "0"], "argument --fps: got 0"),
        (["run", "--goal-tolerance", "-1"], "argument --goal-tolerance: got -1"),
        (["run", "--frame-every", "0"], "argument --frame-every: got 0"),
        (["run", "--frame-every", "-1"], "argument --frame-every: got -1"),
        (["run", "--robots", "-3"], "argument --robots: got -3"),
        (["run", "--robots", "1000000"], r"argument --robots: got 1000000, expected an integer in [1, 100000]"),
        (["run", "--seed", "-1"], "argument --seed: got -1"),
        (["run", "--scenario", "donut"], "argument --scenario: invalid choice: 'donut'"),
        (["run", "--filter", "nope"], "argument --filter: invalid choice: 'nope'"),
        (["run", "--solver", "nope"], "solver: got 'nope'"),
        (["run", "--deadlock", "nope"], "argument --deadlock: invalid choice"),
        (["run", "--trigger", "nope"], "argument --trigger: invalid choice"),
        (["run", "-g", "k4=1"], "k4 must exceed zeta"),
        (["run", "-g", "k9=1"], "-g/--gain: FilterConfig() got an unexpected keyword argument 'k9'"),
        (["run", "-g", "k1"], "-g/--gain: got 'k1', expected KEY=VALUE"),
        (["run", "-p", "radius=-1"], "radius: got -1"),
        (["run", "-p", "color=red"], "-p/--param: scenario 'circle_swap': CircleSwap() got an unexpected keyword"),
        (["run", "--controller", "learned"], "expected --model PATH"),
        (["run", "--model", "x"], "--model: given with --controller 'tracking'"),
        (["run", "--scenario", "custom"], "--scenario custom: missing required parameter(s) starts, reference"),
        (["run", "--gif", str(tmp / "a.webm")], "--gif: got"),
        (["run", "--gif", str(tmp / "a.m4v")], "--gif: got"),
        (["run", "--controller", "learned", "--model", "/etc/passwd"], "--model: got '/etc/passwd'"),
        (["reproduce", "table1", "--out", "/proc/x"], "--out: cannot write to /proc/x"),
        (["reproduce", "table1", "--out", "/dev/null"], "--out: /dev/null exists and is not a folder"),
        (["reproduce", "table1", "--jobs", "0"], "argument --jobs: got 0"),
        (["reproduce", "table1", "--safety-margin", "nan"], "argument --safety-margin: got nan"),
        (["reproduce", "table1", "--solver", "nope"], "--solver: got 'nope'"),
        (["reproduce", "table9"], "argument experiment: invalid choice: 'table9'"),
        (["evaluate", "--out", "/proc/x/t.md"], "--out: cannot write"),
        (["evaluate", "--out", "/dev/null"], "--out: /dev/null exists and is not a regular file"),
        (["evaluate", "--out", str(tmp / "table.md")], "already exists; pass --overwrite"),
        (["evaluate", "--out", str(tmp / "t.json")], "the table is Markdown"),
        (["evaluate", "--episodes", "0"], "argument --episodes: got 0"),
        (["evaluate", "--goal-tolerance", "-1"], "argument --goal-tolerance: got -1"),
        (["evaluate", "--rows", "nope"], "argument --rows: invalid choice"),
        (["evaluate", "--bare", str(tmp / "nope")], "no model here"),
        (["evaluate", "--bare", "/etc/passwd"], "--bare: got '/etc/passwd', a file that is not a model .zip"),
        (["evaluate", "--rows", "learned (bare)"], "--rows: got 'learned (bare)', which needs --bare"),
        (["evaluate", "--rows", "learned (filter) + filter", "random"], "which needs --filtered"),
        (["evaluate", "--filter-arg", "k9=1"], "--filter-arg: FilterConfig() got an unexpected keyword argument"),
        (["evaluate", "--config", str(tmp / "nope.toml")], "no such config file"),
        (["train", "--out-dir", "/proc/x"], "TrainConfig.out_dir: cannot write to /proc/x"),
        (["train", "--out-dir", str(tmp / "a_file")], "TrainConfig.out_dir"),
        (["train", "--num-robots", "-3"], "TrainConfig.num_robots: got -3"),
        (["train", "--seed", "abc"], "argument --seed: got 'abc'"),
        (["train", "--scenario-arg", "color=red"], "unexpected keyword argument 'color'"),
        (["train", "--scenario-arg", "speed=-1"], "speed: got -1"),
        (["train", "--filter", "true", "--filter-arg", "k9=1"], "TrainConfig.filter_kwargs"),
        (["nope"], "argument command: invalid choice: 'nope'"),
    ]


def test_bad_options_and_outputs_fail_at_once_with_one_line(tmp_path, capsys, no_work, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for argv, expected in _bad_cases(tmp_path):
        code, err, seconds = _cli(argv, capsys)
        assert code == 2, (argv, code, err)
        assert len(err) == 1, (argv, err)
        assert expected in err[0], (argv, err[0])
        assert "Traceback" not in err[0]
        assert seconds < 1.0, (argv, seconds)
    # nothing was created on the way (failed commands remove the folders they made)
    assert not (tmp_path / "results").exists() and not (tmp_path / "runs").exists()


def test_debug_shows_the_traceback(capsys):
    from aasoatt_env.errors import ConfigError

    with pytest.raises(ConfigError, match="k4 must exceed zeta"):
        main(["run", "-g", "k4=1", "--debug"])
    with pytest.raises(ConfigError):
        main(["reproduce", "table1", "--solver", "nope", "--debug"])


def test_run_never_overwrites_results_without_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(SMALL_SWAP + ["--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(before) == {"metrics.json", "rollout.npz", "trajectories.png"}
    code, err, _ = _cli(SMALL_SWAP + ["--out", str(out), "--seed", "1", "--controller", "random"], capsys)
    assert code == 2 and "already holds results" in err[0]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main(SMALL_SWAP + ["--out", str(out), "--controller", "random", "--filter", "none", "--overwrite"]) == 0
    assert json.loads((out / "metrics.json").read_text()) != json.loads(before["metrics.json"])
    gif = tmp_path / "a.gif"
    gif.write_bytes(b"earlier")
    code, err, _ = _cli(SMALL_SWAP + ["--gif", str(gif)], capsys)
    assert code == 2 and "--gif" in err[0] and gif.read_bytes() == b"earlier"


def test_reproduce_never_replaces_results(tmp_path, capsys, monkeypatch):
    from aasoatt_env.apps import reproduce

    ran = []

    def fake(name, settings):
        ran.append((name, settings.out, settings.quick))
        d = settings.out / name
        d.mkdir(parents=True, exist_ok=True)
        (d / "README.md").write_text("quick" if settings.quick else "full")

        class R:
            dir = d

        return R(), 0.0

    monkeypatch.setattr(reproduce, "run_experiment", fake)
    monkeypatch.chdir(tmp_path)
    assert main(["reproduce", "table1", "--no-progress"]) == 0
    assert ran == [("table1", Path("results"), False)]
    # --quick goes to results/quick: the full tables stay
    assert main(["reproduce", "all", "--quick", "--no-progress"]) == 0
    assert all(out == Path("results/quick") and quick for _, out, quick in ran[1:])
    assert (tmp_path / "results/table1/README.md").read_text() == "full"
    # into the same folder only with --overwrite
    ran.clear()
    code, err, _ = _cli(["reproduce", "all", "--quick", "--out", "results"], capsys)
    assert code == 2 and "results already holds results (table1)" in err[0] and not ran
    code, err, _ = _cli(["reproduce", "table1", "--quick"], capsys)
    assert code == 2 and "already holds results" in err[0] and not ran
    assert (tmp_path / "results/table1/README.md").read_text() == "full"
    assert main(["reproduce", "table1", "--out", "results", "--overwrite", "--no-progress"]) == 0 and ran


def test_evaluate_keeps_an_existing_table(tmp_path, capsys):
    table = tmp_path / "t.md"
    table.write_text("earlier")
    code, err, _ = _cli(["evaluate", "--rows", "random", "--episodes", "1", "--out", str(table)], capsys)
    assert code == 2 and "already exists" in err[0] and table.read_text() == "earlier"
    (tmp_path / "u.json").write_text("earlier")  # the .json beside the table counts too
    code, err, _ = _cli(["evaluate", "--rows", "random", "--episodes", "1", "--out", str(tmp_path / "u.md")], capsys)
    assert code == 2 and "u.json already exists" in err[0] and not (tmp_path / "u.md").exists()


# --------------------------------------------------------------------------- option errors name the option, exit 2
LONG = "x" * 300


def _refused(tmp: Path) -> list[tuple[list[str], str]]:
    (tmp / "page.md").write_text("earlier page")
    return [
        (["run", "--out", ""], "argument --out: got '', expected a path"),
        (["run", "--out", LONG], "argument --out: got a path of 300 bytes"),
        (["run", "--out", f"new/{LONG}/x"], "argument --out: got a path of 306 bytes"),
        (["run", "--out", "new/a\0b"], "argument --out: got 'new/a\\x00b', expected a path"),
        (["run", "--gif", ""], "argument --gif: got '', expected a path"),
        (["run", "--gif", f"new/{LONG}.gif"], "argument --gif: got a path of 308 bytes"),
        (["run", "--out", "new/run", "--gif", "new2/a.txt"], "--gif: got 'new2/a.txt', expected a file name ending"),
        (["run", "--out", "new/run", "-p", "radius=-1"], "radius: got -1"),
        (["run", "--out", "new/run", "--solver", "nope"], "--solver: got 'nope', expected one of"),
        (["run", "--out", "new/run", "--robots", "0"], "argument --robots: got 0, expected an integer in [1,"),
        (["run", "--out", "new/run", "--fps", "1e3"], "argument --fps: got '1e3', expected an integer in [1, 1000]"),
        (["run", "--out", "new/run", "--seed", "9" * 5000], "argument --seed: got '99999"),
        (["run", "--out", "new/run", "--goal-tolerance", "inf"], "argument --goal-tolerance: got inf"),
        (["list", "--out", "new"], "unrecognized arguments: --out new"),
        (["reproduce", "table1", "--out", ""], "argument --out: got '', expected a path"),
        (["reproduce", "table1", "--out", LONG], "argument --out: got a path of 300 bytes"),
        (["reproduce", "table1", "--page", ""], "argument --page: got '', expected a path"),
        (["reproduce", "table1", "--out", "new", "--page", "new2/t.txt"], "--page: got 'new2/t.txt', expected a "
         "file name ending in one of ['.md']"),
        (["reproduce", "table1", "--out", "new", "--page", "page.md"], "--page: page.md already exists; pass "
         "--overwrite"),
        (["reproduce", "table1", "--out", "new", "--jobs", "-1"], "argument --jobs: got -1"),
    ]


def test_refused_options_name_the_option_exit_2_and_leave_no_folder(tmp_path, capsys, no_work, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for argv, expected in _refused(tmp_path):
        code, err, _ = _cli(argv, capsys)
        assert code == 2, (argv, code, err)
        assert len(err) == 1 and expected in err[0] and len(err[0]) < 400, (argv, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["page.md"], argv  # no folder made, none left


def test_warm_up_prepares_every_part_with_a_line_each(capsys):
    from aasoatt_env import compiled
    from aasoatt_env.apps.cli import main

    assert main(["warm-up"]) == 0
    out = capsys.readouterr().out
    if compiled.available():
        assert "backup layer" in out and "decentralized filter" in out and "kernels ready" in out
    else:
        assert "numpy reference" in out
