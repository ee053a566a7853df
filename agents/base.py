"""The interface shared by every agent and a name registry for the CLI."""

from __future__ import annotations

import inspect
from typing import Any, Protocol, runtime_checkable

import numpy as np

from aasoatt_env.errors import ConfigError

__all__ = ["Agent", "agent_accepts", "agent_names", "get_agent", "register_agent"]


@runtime_checkable
class Agent(Protocol):
    """Anything that maps observations (and the env) to an actions dict."""

    def reset(self, env: Any) -> None:
        """Prepare for a new episode of ``env`` (called after ``env.reset``)."""
        ...

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """Return one ``(2,)`` action per live agent of ``env``."""
        ...


_REGISTRY: dict[str, type] = {}


def register_agent(name: str, cls: type) -> None:
    """Make ``cls`` constructible by name with :func:`get_agent`."""
    _REGISTRY[name] = cls


def agent_accepts(name: str, keyword: str) -> bool:
    """Whether the registered agent ``name`` takes the constructor keyword ``keyword``."""
    factory = _REGISTRY.get(name)
    return factory is not None and keyword in inspect.signature(factory).parameters


def agent_names() -> list[str]:
    """Registered agent names (sorted)."""
    return sorted(_REGISTRY)


def get_agent(name: str, **kwargs: Any) -> Agent:
    """Construct a registered agent by name (unknown names list the choices)."""
    if name not in _REGISTRY:
        raise ConfigError(f"unknown agent/controller {name!r}; known: {sorted(_REGISTRY)}")
    return _REGISTRY[name](**kwargs)
