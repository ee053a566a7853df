"""Exception hierarchy of :mod:`aasoatt_env`, one class per meaning.

Every error the library raises on purpose derives from :class:`AASOATTError`, so
``except aasoatt_env.AASOATTError`` catches all of them.  Errors about bad input
also derive from :class:`ValueError` and call-order mistakes from
:class:`RuntimeError`, so code written against the standard library's
conventions keeps working.  Unknown keyword arguments raise
:class:`UnknownKeywordError`, a :class:`TypeError` with Python's own wording
(some clients probe constructors with extra keywords and expect it).

================================  =================================================
class                             raised when
================================  =================================================
:class:`AASOATTError`             root of the hierarchy
:class:`ConfigError`              a parameter, gain, preset or option is invalid
                                  (``ValueError``)
:class:`ScenarioError`            a scenario is unknown or cannot be realised, e.g.
                                  more robots than fit on the circle
                                  (a :class:`ConfigError`)
:class:`SolverError`              a QP back-end is unknown or not installed
                                  (a :class:`ConfigError`)
:class:`ActionError`              an action passed to ``step`` is malformed (shape,
                                  NaN, unknown or missing agent) (``ValueError``)
:class:`StateError`               a state array handed to the env-free filter core
                                  is malformed (shape, NaN) (``ValueError``)
:class:`DataFileError`            a file to load is missing, corrupted or not what
                                  it claims; the message names the file
                                  (``ValueError``)
:class:`UsageError`               a method is called when the object is not ready
                                  for it, e.g. ``step`` before ``reset``, wrapping
                                  an env twice (``RuntimeError``)
:class:`ResetNeeded`              the env must be reset first (a :class:`UsageError`)
:class:`UnknownKeywordError`      an unknown keyword argument or option name
                                  (``TypeError``, Python's wording)
================================  =================================================
"""

from __future__ import annotations

__all__ = [
    "AASOATTError",
    "ActionError",
    "ConfigError",
    "DataFileError",
    "ResetNeeded",
    "ScenarioError",
    "SolverError",
    "StateError",
    "UnknownKeywordError",
    "UsageError",
]


class AASOATTError(Exception):
    """Root of every exception raised on purpose by :mod:`aasoatt_env`."""


class ConfigError(AASOATTError, ValueError):
    """A configuration value is invalid ("got X, expected Y")."""


class ScenarioError(ConfigError):
    """A scenario is unknown or its parameters cannot be realised."""


class SolverError(ConfigError):
    """A QP solver is unknown or unavailable."""


class ActionError(AASOATTError, ValueError):
    """An action passed to ``step`` is malformed."""


class StateError(AASOATTError, ValueError):
    """A state array given to the filter core is malformed (shape, non-finite values)."""


class DataFileError(AASOATTError, ValueError):
    """A file is missing, corrupted or of the wrong kind; the message names it."""


class UsageError(AASOATTError, RuntimeError):
    """A method was called when the object is not in a state that allows it."""


class ResetNeeded(UsageError):
    """The environment has to be reset before this call."""


class UnknownKeywordError(AASOATTError, TypeError):
    """An unknown keyword argument or option name (worded like Python's own ``TypeError``)."""
