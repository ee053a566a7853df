"""Shared fixtures of the test suite."""

from __future__ import annotations

import pytest


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any simulation, experiment, evaluation episode or training started by a command fails the test."""

    def boom(*args, **kwargs):
        raise AssertionError("the command started work before checking its options")

    import aasoatt_env.apps.cli as cli
    import aasoatt_env.apps.reproduce as reproduce
    import train.evaluate as evaluate
    import train.train as train

    monkeypatch.setattr(cli, "run_episode", boom)
    monkeypatch.setattr(reproduce, "run_experiment", boom)
    monkeypatch.setattr(evaluate, "evaluate_agent", boom)
    monkeypatch.setattr(train, "make_vec_env", boom)
