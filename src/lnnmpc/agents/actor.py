"""Who chooses an agent's actions when it is evaluated: its MPPI planner (the protocol) or its policy prior alone.

    agent = with_actor(agent, "prior")      # agent.act is now the policy prior's act; everything else unchanged

TD-MPC2 acts with MPPI over its world model, the policy prior seeding 24 of the 512 samples; its ``act(mpc=False)``
acts with the prior alone. Comparing the two on one checkpoint separates what the world model's planning adds (or
costs) from what the policy has learned, e.g. when a run's returns collapse late in training.
"""

from __future__ import annotations

from typing import Any

ACTORS = ("planner", "prior")


class PriorActing:
    """``agent`` with :meth:`act` replaced by the agent's ``act_prior`` (same signature, same carry); every other
    attribute is the wrapped agent's."""

    def __init__(self, agent: Any):
        if not hasattr(agent, "act_prior"):
            raise ValueError(f"{type(agent).__name__} has no policy prior to act with (no act_prior)")
        self.agent = agent

    def __getattr__(self, name: str) -> Any:
        if name == "agent":  # not set yet (copy and pickle build the object without __init__): no recursion
            raise AttributeError(name)
        return getattr(self.agent, name)

    def act(self, state, carry, obs, dt, key, *, explore: bool, first_step):
        """The policy prior's action (A,) and the next carry, as ``agent.act_prior``."""
        return self.agent.act_prior(state, carry, obs, dt, key, explore=explore, first_step=first_step)


def check_actor(actor: str) -> None:
    """Raises ValueError naming an unknown ``actor`` and the known ones (:data:`ACTORS`)."""
    if actor not in ACTORS:
        raise ValueError(f"unknown actor {actor!r}; known: {', '.join(ACTORS)}")


def with_actor(agent: Any, actor: str) -> Any:
    """``agent`` acting with ``actor``: "planner" (MPPI, the agent itself) or "prior" (:class:`PriorActing`);
    :func:`check_actor` refuses any other."""
    check_actor(actor)
    return agent if actor == "planner" else PriorActing(agent)
