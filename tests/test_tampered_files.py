"""Tampered run folders: every crafted file is refused before anything in the process changes.

Each case edits one file of a copy of a finished run and loads it: the loader must raise
:class:`DataFileError` naming the file, quickly (sizes are checked before anything is
allocated), and a second, good run evaluated in the same process must act exactly as before
(nothing the crafted file names was set: a dunder name such as ``policy.action_net.weight.__class__``
in ``pytorch_variables.pth`` once overwrote ``torch.nn.Parameter.data`` for the whole process).
"""

from __future__ import annotations

import io
import json
import shutil
import struct
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import tiny_train_config

from aasoatt_env.errors import DataFileError

torch = pytest.importorskip("torch")
pytest.importorskip("stable_baselines3")


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two finished tiny runs: one to tamper with, one to evaluate before and after."""
    from train.train import train

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("runs")
    return (train(tiny_train_config(out, run_name="victim")).parent,
            train(tiny_train_config(out, run_name="good", seed=1)).parent)


def _behaviour(run: Path) -> tuple[np.ndarray, float]:
    """Actions of ``run``'s policy on fixed observations, and one evaluated episode's RMSE."""
    from agents.learned import LearnedAgent
    from train.evaluate import evaluate

    agent = LearnedAgent.load(run)
    obs = np.linspace(-2.0, 2.0, 5 * agent.model.observation_space.shape[0], dtype=np.float32).reshape(5, -1)
    actions, _ = agent.model.predict(agent.normalize(obs), deterministic=True)
    (row,) = evaluate(run, episodes=1, rows=["learned (bare)"])
    return np.asarray(actions), row.rmse


def _rewrite_zip(path: Path, replace: dict[str, bytes]) -> None:
    tmp = path.with_suffix(".tmp")
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(tmp, "w") as dst:
        names = src.namelist()
        for name in names:
            dst.writestr(name, replace.get(name, src.read(name)))
        for name, content in replace.items():
            if name not in names:
                dst.writestr(name, content)
    tmp.replace(path)


def _tensors(**state: object) -> bytes:
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


def _policy_state(run: Path) -> dict:
    with zipfile.ZipFile(run / "model.zip") as z:
        return torch.load(io.BytesIO(z.read("policy.pth")), weights_only=True)


def _edit_policy(run: Path, edit) -> None:  # noqa: ANN001
    state = dict(_policy_state(run))
    edit(state)
    _rewrite_zip(run / "model.zip", {"policy.pth": _tensors(**state)})


def _edit_data(run: Path, edit) -> None:  # noqa: ANN001
    with zipfile.ZipFile(run / "model.zip") as z:
        data = json.loads(z.read("data"))
    _rewrite_zip(run / "model.zip", {"data": edit(data) if callable(edit) else edit})


def _declare_size(path: Path, member: str, size: int) -> None:
    """Patch the uncompressed size ``member`` declares in the zip's central directory."""
    raw = bytearray(path.read_bytes())
    pos = raw.find(b"PK\x01\x02")
    while pos >= 0:
        name_len = struct.unpack_from("<H", raw, pos + 28)[0]
        if raw[pos + 46:pos + 46 + name_len].decode() == member:
            struct.pack_into("<I", raw, pos + 24, size)
            break
        pos = raw.find(b"PK\x01\x02", pos + 4)
    path.write_bytes(bytes(raw))


def _npz_header_claiming(shape: tuple[int, ...], real: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buf.getvalue() + real.tobytes()


def _edit_stats(run: Path, **arrays: np.ndarray) -> None:
    with np.load(run / "normalization.npz") as z:
        stats = dict(z)
    np.savez(run / "normalization.npz", **{**stats, **arrays})


def _policy_kwargs(run: Path, **kwargs: object) -> None:
    _edit_data(run, lambda d: json.dumps({**d, "policy_kwargs": kwargs}))


CASES = {
    # pytorch_variables.pth names attributes SB3 would set: none may be set, PPO keeps none
    "dunder name in pytorch_variables": (
        "model.zip", lambda r: _rewrite_zip(r / "model.zip", {"pytorch_variables.pth": _tensors(
            **{"policy.action_net.weight.__class__": torch.zeros(2)})}), r"pytorch_variables.pth: unexpected entries"),
    "dotted name in pytorch_variables": (
        "model.zip", lambda r: _rewrite_zip(r / "model.zip", {"pytorch_variables.pth": _tensors(
            **{"policy.action_net.weight": torch.zeros(2, 8)})}), r"pytorch_variables.pth: unexpected entries"),
    # policy.pth: exactly the network's names and shapes, finite floats
    "dunder name in policy.pth": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s.update({"action_net.weight.__class__": torch.zeros(1)})),
        r"policy.pth: unexpected entries 'action_net.weight.__class__'"),
    "unknown dotted name in policy.pth": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s.update({"optimizer.param_groups.0.lr": torch.zeros(1)})),
        r"policy.pth: unexpected entries"),
    "missing parameter": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s.pop("action_net.bias")),
        r"policy.pth: missing entries 'action_net.bias'"),
    "wrong shape": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s.update({"action_net.weight": s["action_net.weight"].T})),
        r"policy.pth: 'action_net.weight' is torch.float32 \(8, 2\), expected a float tensor of shape \(2, 8\)"),
    "integer weights": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s.update({"value_net.bias": torch.zeros(1).long()})),
        r"'value_net.bias' is torch.int64"),
    "NaN weights": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s["mlp_extractor.policy_net.0.weight"].fill_(float("nan"))),
        r"'mlp_extractor.policy_net.0.weight' holds non-finite values"),
    "inf log_std": (
        "model.zip", lambda r: _edit_policy(r, lambda s: s["log_std"].fill_(float("inf"))),
        r"'log_std' holds non-finite"),
    # the zip's data: bounded networks, plain JSON, bounded nesting
    "net_arch [4096]*16": (
        "model.zip", lambda r: _policy_kwargs(r, net_arch=[4096] * 16),
        r"policy_kwargs: net_arch: a network of [\d,]+ parameters, expected at most 4,194,304"),
    "net_arch of 10**9": (
        "model.zip", lambda r: _policy_kwargs(r, net_arch={"pi": [10**9]}),
        r"net_arch: got \{'pi': \[1000000000\]\}, expected a list of at most 16 layer sizes"),
    "deep JSON data": ("model.zip", lambda r: _edit_data(r, b"[" * 100_000),
                       r"data: not a readable JSON file \(nested"),
    "NaN log_std_init": (
        "model.zip", lambda r: _policy_kwargs(r, log_std_init="NaN"),
        r"log_std_init: got NaN"),
    "huge declared member": ("model.zip", lambda r: _declare_size(r / "model.zip", "policy.pth", 2**31),
                             r"entry 'policy.pth' declares 2,147,483,648 bytes"),
    # normalization.npz: names, header shapes (checked before the data is read), finite, ranges
    "header claiming 10**9 floats": (
        "normalization.npz", lambda r: _rewrite_zip(r / "normalization.npz", {"mean.npy": _npz_header_claiming(
            (10**9,), np.zeros(8))}), r"'mean' declares [\d,]+ bytes|'mean' has shape \(1000000000,\)"),
    "NaN statistics": ("normalization.npz", lambda r: _edit_stats(r, var=np.full(50, np.nan)),
                       r"'var' holds non-finite values"),
    "extra array": ("normalization.npz", lambda r: _edit_stats(r, evil=np.ones(1)), r"got arrays .*'evil'"),
    "object array": ("normalization.npz", lambda r: _edit_stats(r, mean=np.array([{"a": 1}], dtype=object)),
                     r"normalization.npz: not a readable .npz|dtype object"),
    # policy.json: every field, and the settings the weights were trained with
    "deep policy.json": ("policy.json", lambda r: (r / "policy.json").write_text("[" * 100_000),
                         r"policy.json: not a readable JSON file \(nested 100000 levels deep"),
    "normalize_obs edited": ("policy.json", lambda r: _edit_spec(r, normalize_obs=False),
                             r"differs from the settings its weights were trained with \(normalize_obs: False"),
    "action_mode edited": ("policy.json", lambda r: _edit_spec(r, env={"action_mode": "wheel"}),
                           r"action_mode: 'wheel' \(trained with 'point'\)"),
    "decision_interval edited": ("policy.json", lambda r: _edit_spec(r, env={"decision_interval": 10}),
                                 r"decision_interval: 10 \(trained with 20\)"),
    "unknown key": ("policy.json", lambda r: _edit_spec(r, evil=1), r"unexpected keys \['evil'\]"),
    "format 2": ("policy.json", lambda r: _edit_spec(r, format=2), r"format: got 2, expected 1"),
    "filter dt edited": ("policy.json", lambda r: _edit_spec(r, filter={"dt": 0.01}),
                         r"filter dt: got 0.01, expected the env's dt = 0.005"),
}


def _edit_spec(run: Path, env: dict | None = None, **fields: object) -> None:
    spec = json.loads((run / "policy.json").read_text())
    spec["env"].update(env or {})
    spec.update(fields)
    (run / "policy.json").write_text(json.dumps(spec))


def test_every_case_is_a_different_file_edit():
    assert len(CASES) >= 25


@pytest.mark.parametrize("case", list(CASES))
def test_tampered_files_are_refused_before_anything_changes(runs, tmp_path, case):
    from agents.learned import LearnedAgent

    victim, good = runs
    before = _behaviour(good)
    name, tamper, match = CASES[case]
    run = tmp_path / "run"
    shutil.copytree(victim, run)
    tamper(run)
    t0 = time.perf_counter()
    with pytest.raises(DataFileError, match=match) as exc:
        LearnedAgent.load(run)
    assert time.perf_counter() - t0 < 2.0
    assert name in str(exc.value)
    assert "data" not in torch.nn.Parameter.__dict__  # nothing the file names was set on a class
    after = _behaviour(good)
    assert np.array_equal(before[0], after[0]) and before[1] == after[1]


def test_a_deep_policy_json_is_one_line_status_2_in_the_commands(runs, tmp_path, capsys):
    from aasoatt_env.apps.cli import main

    run = tmp_path / "run"
    shutil.copytree(runs[0], run)
    (run / "policy.json").write_text("[" * 100_000)
    for argv in (["evaluate", "--bare", str(run), "--episodes", "1"],
                 ["run", "--controller", "learned", "--model", str(run), "-q"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "policy.json: not a readable JSON file (nested" in err
        assert "Traceback" not in err and "RecursionError" not in err
