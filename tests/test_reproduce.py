"""Tests of ``aasoatt reproduce``: the quick suite runs end to end and writes sane files.

The end-to-end tests (``all --quick``, about a minute) are marked ``slow``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from aasoatt_env.apps.reproduce import EXPERIMENTS, main, paper
from aasoatt_env.apps.reproduce.report import RunSpec, md_table, rel_diff, run_spec

QUICK_FILES = {
    "table1": ["table1_errors.png"],
    "compare-ca": ["compare_ca_trajectories.png", "compare_ca_speed.png"],
    "table2": ["fig2_distance_profiles.png", "table2_min_distance.png"],
    "deadlock-triggers": ["fig3a_velocity_profiles.png"],
    "table3": ["table3_vs_paper.png"],
    "swarm100": ["swarm100_trajectories.png"],
    "obstacles": ["fig5_snapshots.png"],
}


@pytest.fixture(scope="module")
def quick_results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("results")
    assert main(["all", "--quick", "--out", str(out), "--no-progress", "--page", str(out / "page.md")]) == 0
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_all_quick_writes_files(quick_results: Path) -> None:
    assert set(QUICK_FILES) == set(EXPERIMENTS)
    for name, figs in QUICK_FILES.items():
        d = quick_results / name
        assert (d / f"{name}.csv").is_file(), name
        md = (d / "README.md").read_text()
        assert "Wall time of this experiment" in md
        assert "QUICK MODE" in md
        for fig in figs:
            png = d / fig
            assert png.is_file() and png.stat().st_size > 1000, png
            assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = (quick_results / "SUMMARY.md").read_text()
    assert "Total wall time" in summary
    page = (quick_results / "page.md").read_text()
    assert f"aasoatt reproduce all --quick --out {quick_results} --no-progress --page" in page.splitlines()[5]
    for name in EXPERIMENTS:  # every experiment's results table, as in its README
        readme = (quick_results / name / "README.md").read_text()
        table = readme[readme.index("## Results"):].split("\n\n")[1]
        assert table in page, name


@pytest.mark.slow
def test_csv_numbers_finite(quick_results: Path) -> None:
    for name in EXPERIMENTS:
        rows = _rows(quick_results / name / f"{name}.csv")
        assert rows, name
        for row in rows:
            for key in ("rmse", "mae", "std"):
                v = float(row[key])
                assert math.isfinite(v) and v >= 0, (name, key, v)
            # std^2 = rmse^2 - mae^2 (population std over pooled samples)
            r, m, s = float(row["rmse"]), float(row["mae"]), float(row["std"])
            assert abs(s * s - (r * r - m * m)) < 1e-9
            if name != "table1":
                assert math.isfinite(float(row["intervention_time"]))


@pytest.mark.slow
def test_markdown_has_paper_columns(quick_results: Path) -> None:
    md = (quick_results / "compare-ca" / "README.md").read_text()
    for col in ("IT [s] paper", "IT [s] ours", "RMSE paper", "RMSE ours", "MAE paper", "std paper", "rel."):
        assert col in md
    assert "4.4850" in md and "0.7888" in md  # the paper's "ours" tuple
    md1 = (quick_results / "table1" / "README.md").read_text()
    assert "0.2000" in md1 and "SBC k3=80" in md1
    md3 = (quick_results / "table3" / "README.md").read_text()
    assert "eqn.12a" in md3 and "eqn.13" in md3


@pytest.mark.slow
def test_table1_ours_beats_sbc_k3_10(quick_results: Path) -> None:
    rows = {(r["trajectory"], r["controller"]): r for r in _rows(quick_results / "table1" / "table1.csv")}
    for traj in ("straight", "sine", "circle"):
        assert float(rows[(traj, "ours k3=1")]["rmse"]) < float(rows[(traj, "SBC k3=10")]["rmse"])
        # SBC with the larger gain tracks better than with the smaller one
        assert float(rows[(traj, "SBC k3=80")]["rmse"]) < float(rows[(traj, "SBC k3=10")]["rmse"])


@pytest.mark.slow
def test_quick_runs_are_safe_and_solved(quick_results: Path) -> None:
    rows = _rows(quick_results / "compare-ca" / "compare-ca.csv")
    for row in rows:
        assert float(row["min_robot_gap_full"]) > -0.01, row["key"]
    # the adaptive-distance barrier (eqn.n7) is the most conservative, as in the paper
    it = {r["key"]: float(r["intervention_time"]) for r in rows}
    assert it["eqn.n7"] == max(it.values())


@pytest.mark.slow
def test_table1_deterministic_across_jobs(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["table1", "--quick", "--out", str(a), "--no-progress"]) == 0
    assert main(["table1", "--quick", "--out", str(b), "--no-progress", "--jobs", "2"]) == 0
    ra, rb = _rows(a / "table1" / "table1.csv"), _rows(b / "table1" / "table1.csv")
    for x, y in zip(ra, rb):
        assert x["key"] == y["key"]
        for k in ("rmse", "mae", "std", "max_tracking_error"):
            assert x[k] == y[k]


def test_bad_arguments() -> None:
    with pytest.raises(SystemExit):
        main(["nope"])
    with pytest.raises(SystemExit) as exc:
        main(["table1", "--jobs", "0"])
    assert exc.value.code == 2
    assert main(["table1", "--solver", "no-such-solver"]) == 2


def test_helpers() -> None:
    assert rel_diff(1.1, 1.0) == pytest.approx(0.1)
    assert rel_diff(None, 1.0) is None and rel_diff(1.0, None) is None
    table = md_table(["a", "b"], [[1, 0.5], ["x", None]])
    assert table.splitlines()[2] == "| 1 | 0.5000 |" and "| x | - |" in table
    assert paper.COMPARE_CA["ours"]["rmse"] == 0.7888
    assert paper.TABLE2["eqn.n4"]["rmse"][35] is None
    assert paper.TABLE3[60]["eqn.13"]["intervention_time"] == 18.6150


def test_window_cuts_rollout() -> None:
    from aasoatt_env.analysis.recording import run_episode
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from agents.baselines import TrackingController

    ro, _ = run_episode(
        AASOATTParallelEnv("tracking", trajectory="straight", duration=1.0), TrackingController(saturate=True), seed=0
    )
    cut = ro.window(0.5)
    assert cut.times[-1] <= 0.5 + 1e-9 and cut.n_steps == int(np.sum(ro.times <= 0.5 + 1e-9)) < ro.n_steps
    np.testing.assert_array_equal(cut.positions, ro.positions[: cut.n_steps])
    assert ro.window(None) is ro and ro.window(10.0) is ro
    # the runner's paper metrics are over the window: a 0.5 s window of the same run
    spec = RunSpec("w", "tracking", dict(trajectory="straight", duration=1.0), "tracking", 1.0, 4.0, window=0.5)
    res = run_spec(spec)
    errs = np.linalg.norm(cut.positions - cut.references, axis=-1)
    assert res.metrics["rmse"] == pytest.approx(float(np.sqrt(np.mean(errs**2))), rel=1e-12)


def test_page_is_headed_by_the_command_and_never_overwritten_silently(tmp_path, monkeypatch, capsys) -> None:
    import aasoatt_env.apps.reproduce as reproduce
    from aasoatt_env.apps.reproduce.report import Report

    def fake(exp, s):
        return Report(exp.name, exp.title, s.out, [{"key": "k", "rmse": 0.5}], ["one setting"],
                      ["## Results\n\n| a |\n|---|\n| 1 |", "## Findings\n\n- f"], [])

    monkeypatch.setattr(reproduce, "run", fake)
    monkeypatch.chdir(tmp_path)
    argv = ["table1", "--quick", "--out", "res", "--page", "docs/results.md", "--no-progress"]
    assert main(argv) == 0
    page = (tmp_path / "docs/results.md").read_text().splitlines()
    assert page[0].startswith("# ") and page[4:7] == ["```", "aasoatt reproduce " + " ".join(argv), "```"]
    assert "## Table I - single-robot trajectory tracking" in page and "### Results" in page and "- one setting" in page
    assert (tmp_path / "res/table1/table1.csv").read_text().splitlines() == ["key,rmse", "k,0.5"]
    assert main([*argv[:2], "--out", "res2", *argv[4:]]) == 2  # an existing page needs --overwrite
    assert "--page: docs/results.md already exists; pass --overwrite" in capsys.readouterr().err
    assert not (tmp_path / "res2").exists()


def test_an_experiment_declares_runs_and_columns_and_the_runner_tabulates_them(tmp_path) -> None:
    from aasoatt_env.apps.reproduce.report import Experiment, Settings, col, compared, run

    class Tiny(Experiment):
        name, title, metrics = "tiny", "Tiny", ("rmse",)

        def _specs(self, s):
            return [RunSpec(f"k3={k3}", "tracking", dict(trajectory="straight", duration=0.5), "tracking", k3, 4.0,
                            meta={"k3": k3}) for k3 in (1.0, 2.0)]

        def _paper(self, spec):
            return {"rmse": 0.01} if spec.meta["k3"] == 1.0 else None

        def _columns(self, s):
            return [col("k3", "k3", 1), *compared(self.metrics)]

        def _findings(self, s, res):
            return [f"{len(res)} runs"]

    report = run(Tiny(), Settings(out=tmp_path, progress=False))
    first, second = report.rows
    assert first["paper_rmse"] == 0.01 and first["rel_rmse"] == pytest.approx(first["rmse"] / 0.01 - 1)
    assert second["paper_rmse"] is None and second["rel_rmse"] is None
    table = report.sections[0].splitlines()
    assert table[2] == "| k3 | RMSE paper | RMSE ours | rel. |"
    assert table[4] == f"| 1.0 | 0.0100 | {first['rmse']:.4f} | {100 * first['rel_rmse']:+.1f}% |"
    assert table[5] == f"| 2.0 | - | {second['rmse']:.4f} | - |" and report.sections[-1] == "## Findings\n\n- 2 runs"
    csv_path, md_path = report.write(1.0, "cmd")
    assert _rows(csv_path)[1]["paper_rmse"] == "" and "Command: `cmd`" in md_path.read_text()
    assert sorted(p.name for p in report.dir.iterdir()) == ["README.md", "tiny.csv"]
