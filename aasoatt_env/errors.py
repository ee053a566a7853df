"""Exceptions of :mod:`aasoatt_env`: bad input is also a ``ValueError``, misuse a ``RuntimeError``."""

from __future__ import annotations

__all__ = ["AASOATTError", "ActionError", "ConfigError", "DataFileError", "ResetNeeded", "ScenarioError",
           "SolverError", "StateError", "UnknownKeywordError", "UsageError"]


class AASOATTError(Exception):
    """Root of every exception raised on purpose by :mod:`aasoatt_env`."""


class ConfigError(AASOATTError, ValueError):
    """A configuration value is invalid ("got X, expected Y")."""


class ScenarioError(ConfigError):
    """A scenario is unknown or its parameters cannot be realised (e.g. more robots than fit on the circle)."""


class SolverError(ConfigError):
    """A QP solver is unknown or unavailable."""


class ActionError(AASOATTError, ValueError):
    """An action passed to ``step`` is malformed (shape, dtype, NaN, unknown or missing agent)."""


class StateError(AASOATTError, ValueError):
    """A state array given to the filter core is malformed (shape, non-finite values)."""


class DataFileError(AASOATTError, ValueError):
    """A file is missing, corrupted or of the wrong kind; the message names it."""


class UsageError(AASOATTError, RuntimeError):
    """A method was called when the object is not ready for it (``step`` before ``reset``, wrapping twice)."""


class ResetNeeded(UsageError):
    """The environment has to be reset before this call."""


class UnknownKeywordError(AASOATTError, TypeError):
    """An unknown keyword argument or option name, worded as Python's ``TypeError`` (TorchRL's ``GymEnv`` probes it)."""
