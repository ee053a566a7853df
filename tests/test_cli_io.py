"""What the commands share: light imports, atomic writes that survive an interrupt, progress lines."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.cli_support import PARTIAL, OutputPlan, atomic_write, progress, staged

# (scipy's modules below: a third of `aasoatt --help`'s time; asked by large teams and some solvers only)
HEAVY = ("torch", "matplotlib", "numba", "stable_baselines3", "ray", "pygame", "imageio", "scipy.spatial",
         "scipy.optimize", "scipy.sparse.linalg")


def test_importing_the_command_line_loads_no_heavy_library():
    code = f"import sys, aasoatt_env.apps.cli; print([m for m in {HEAVY!r} if m in sys.modules])"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def _half_then(exc: BaseException):
    def write(tmp: Path) -> None:
        tmp.write_bytes(b"half a file")
        raise exc

    return write


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError("disk full")])
def test_atomic_write_interrupted_half_way_keeps_the_earlier_file(tmp_path, exc):
    target = tmp_path / "rollout.npz"
    with pytest.raises(type(exc)):
        atomic_write(target, _half_then(exc))
    assert list(tmp_path.iterdir()) == []  # no partial file, no temporary file
    target.write_bytes(b"earlier")
    with pytest.raises(type(exc)):
        atomic_write(target, _half_then(exc))
    assert [p.name for p in tmp_path.iterdir()] == ["rollout.npz"] and target.read_bytes() == b"earlier"
    atomic_write(target, lambda tmp: tmp.write_bytes(b"new"))
    assert [p.name for p in tmp_path.iterdir()] == ["rollout.npz"] and target.read_bytes() == b"new"


def test_staged_files_are_replaced_all_or_none(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.png"
    a.write_text("old a")
    with pytest.raises(KeyboardInterrupt), staged(a, b) as (ta, tb):
        ta.write_text("new a")
        tb.write_bytes(b"half")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"] and a.read_text() == "old a"
    with staged(a, b) as (ta, tb):
        assert ta.suffix == ".json" and tb.suffix == ".png" and PARTIAL in ta.name  # writers pick formats by suffix
        ta.write_text("new a")
        tb.write_bytes(b"new b")
    assert a.read_text() == "new a" and b.read_bytes() == b"new b"


def test_rollout_save_is_atomic(tmp_path, monkeypatch):
    ro = Rollout(dt=0.1, times=[0.0, 0.1], positions=np.zeros((2, 1, 2)), velocities=np.zeros((2, 1, 2)),
                 headings=np.zeros((2, 1)), references=np.zeros((2, 1, 2)), reference_velocities=np.zeros((2, 1, 2)),
                 goals=[[0.0, 0.0]], radii=[0.5])
    ro.save(tmp_path / "r")  # numpy's convention: .npz appended
    assert [p.name for p in tmp_path.iterdir()] == ["r.npz"]
    np.testing.assert_array_equal(Rollout.load(tmp_path / "r.npz").positions, ro.positions)

    def broken(path, **arrays):
        Path(path).write_bytes(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", broken)
    with pytest.raises(KeyboardInterrupt):
        ro.save(tmp_path / "r.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["r.npz"]
    np.testing.assert_array_equal(Rollout.load(tmp_path / "r.npz").positions, ro.positions)


def test_debris_of_a_killed_run_is_not_taken_for_results(tmp_path):
    (tmp_path / f".rollout.123{PARTIAL}.npz").write_bytes(b"debris of a kill -9")
    assert OutputPlan(overwrite=False).folder(tmp_path, "--out", entries=None) == tmp_path


_INTERRUPTED_RUN = """
    import os, signal, sys
    import numpy as np
    from aasoatt_env.apps.cli import main

    signal.signal(signal.SIGINT, signal.default_int_handler)  # (a runner started in the background ignores SIGINT)
    real = np.savez_compressed

    def interrupted(path, **arrays):  # Ctrl-C half way through writing rollout.npz
        with open(path, "wb") as fh:
            fh.write(b"PK\\x03\\x04 half an archive")
        os.kill(os.getpid(), signal.SIGINT)
        real(path, **arrays)

    np.savez_compressed = interrupted
    sys.exit(main(sys.argv[1:]))
"""


def test_ctrl_c_while_run_writes_leaves_no_partial_file_and_the_folder_reusable(tmp_path):
    out = tmp_path / "D"
    argv = ["run", "--robots", "2", "-p", "radius=1.0", "-p", "duration=0.3", "--filter", "none", "-q",
            "--out", str(out)]
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(_INTERRUPTED_RUN), *argv], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 130 and "interrupted" in res.stderr, res.stderr
    assert not out.exists() or list(out.iterdir()) == []  # neither metrics.json nor a half rollout.npz, nor debris
    from aasoatt_env.apps.cli import main

    assert main(argv) == 0  # the next run is not refused for "already holding results"
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "rollout.npz", "trajectories.png"]
    assert json.loads((out / "metrics.json").read_text())["n_robots"] == 2


def test_progress_without_tqdm_prints_rate_and_time_left(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)
    bar = progress(20, "episode", unit="step")
    for _ in range(20):
        bar.update(1)
    bar.set_postfix_str("ignored")
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 10 and lines[-1].startswith("episode: 20/20 steps, ") and "step/s" in lines[-1]
    assert lines[0].startswith("episode: 2/20 steps") and lines[0].endswith(" s left")
    quiet = progress(5, "x", enabled=False)
    quiet.update(5)
    assert capsys.readouterr().err == ""


def test_make_tensor_env_without_torch_says_what_to_install():
    code = ("import sys; sys.modules['torch'] = None\nimport aasoatt_env\ntry:\n    aasoatt_env.make_tensor_env\n"
            "except ImportError as exc:\n    print(exc)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "make_tensor_env needs torch: pip install torch (or the 'train' extra)"
