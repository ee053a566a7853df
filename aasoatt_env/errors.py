"""Exception hierarchy of :mod:`aasoatt_env`.

Every error the library raises on purpose derives from :class:`AASOATTError`, so
``except aasoatt_env.AASOATTError`` catches all of them.  Errors about bad input
also derive from :class:`ValueError`, so code written against the standard
library's conventions keeps working.

================================  =================================================
class                             raised when
================================  =================================================
:class:`AASOATTError`             root of the hierarchy
:class:`ConfigError`              a parameter, gain, preset or option is invalid
:class:`ActionError`              an action dict/array is malformed (shape, NaN,
                                  unknown or missing agent)
:class:`ScenarioError`            a scenario is unknown or cannot be built (e.g.
                                  more robots than fit on the circle)
:class:`SolverError`              a QP back-end is unknown or not installed
================================  =================================================
"""

from __future__ import annotations

__all__ = [
    "AASOATTError",
    "ActionError",
    "ConfigError",
    "ScenarioError",
    "SolverError",
]


class AASOATTError(Exception):
    """Root of every exception raised on purpose by :mod:`aasoatt_env`."""


class ConfigError(AASOATTError, ValueError):
    """A configuration value is invalid ("got X, expected Y")."""


class ActionError(AASOATTError, ValueError):
    """An action passed to ``step`` is malformed."""


class ScenarioError(AASOATTError, ValueError):
    """A scenario is unknown or its parameters cannot be realised."""


class SolverError(AASOATTError, ValueError):
    """A QP solver is unknown or unavailable."""
