"""Controllers that act on an :class:`aasoatt_env.AASOATTParallelEnv` (bare or filtered).

=========================  ====================================================
agent                      what it does
=========================  ====================================================
:class:`TrackingController`  the paper's tracking law eqn.11-12 (``k3 = 1``, ``k4 = 4``)
:class:`PDController`        SBC's PD nominal ``a = -k3 (p - p_d) - k4 v`` (Table I)
:class:`RandomAgent`         uniform random actions from the action spaces
:class:`HostileAgent`        every robot accelerates at its nearest neighbour
adversaries                  :data:`agents.adversaries.ADVERSARIES`: spin-up, burst,
                             bang-bang, chase nearest / target, uniform noise
=========================  ====================================================

Every agent has ``reset(env)`` and ``act(observations, env) -> actions`` where
``actions`` maps each live agent to a ``(2,)`` float32 action; learned policies
implement the same two methods.
"""

from agents.adversaries import ADVERSARIES, HostileAgent
from agents.base import Agent, get_agent
from agents.baselines import PDController, RandomAgent, TrackingController

__all__ = ["ADVERSARIES", "Agent", "HostileAgent", "PDController", "RandomAgent", "TrackingController", "get_agent"]
