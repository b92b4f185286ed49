"""The training schedule in loop iterations: how many environment steps a number of iterations takes, how many
iterations a step budget needs, and the chunk length that ends a run at its budget.

One loop iteration steps every environment of a seed once (``per_iteration`` environment steps per seed, action
repeat included), except the iteration after the last step of an episode, which resets the environments and
takes no step (episodes have a fixed length of ``episode_length`` agent steps; :mod:`lnnmpc.train.loop`). Pure
integer arithmetic, so ``train --check`` can say where a run will end before anything is compiled.
"""

from __future__ import annotations

import math


def steps_after(iterations: int, per_iteration: int, episode_length: int) -> int:
    """Environment steps per seed taken by the first ``iterations`` iterations from a fresh start."""
    return per_iteration * (iterations - iterations // (episode_length + 1))


def seed_iterations(seed_steps: int, per_iteration: int) -> int:
    """Loop iterations of the random seed phase of ``seed_steps`` environment steps per seed."""
    return math.ceil(seed_steps / per_iteration)


def iterations_for(steps: int, per_iteration: int, episode_length: int) -> int:
    """The fewest iterations from a fresh start whose :func:`steps_after` reaches ``steps``."""
    stepping = max(0, math.ceil(steps / per_iteration))
    return stepping + max(0, stepping - 1) // episode_length


def chunk_length(steps: int, seed_iterations: int, per_iteration: int, episode_length: int, eval_every: int,
                 max_chunk: int) -> int:
    """Iterations per training chunk: the training iterations after the seed phase that the budget ``steps``
    needs, in as few equal chunks of at most ``eval_every`` environment steps and ``max_chunk`` iterations as
    hold them, so that the last chunk ends less than one iteration per chunk past ``steps`` (a fixed length of
    ``eval_every`` steps could end a whole chunk past it). A budget the seed phase covers gets the longest chunk."""
    cap = max(1, min(eval_every // per_iteration, max_chunk))
    training = iterations_for(steps, per_iteration, episode_length) - seed_iterations
    if training <= 0:
        return cap
    return math.ceil(training / math.ceil(training / cap))


def final_steps(steps: int, seed_iterations: int, chunk: int, per_iteration: int, episode_length: int) -> int:
    """Environment steps per seed at which a run with this schedule ends (the first chunk boundary at or past
    ``steps``; the seed phase alone when it reaches ``steps``)."""
    training = iterations_for(steps, per_iteration, episode_length) - seed_iterations
    chunks = max(0, math.ceil(training / chunk))
    return steps_after(seed_iterations + chunks * chunk, per_iteration, episode_length)
