"""The chunk schedule (lnnmpc.train.schedule) against a step-by-step count of the loop's iterations: every episode
is ``episode_length`` stepping iterations and one reset iteration that takes no environment step."""

from __future__ import annotations

import itertools

from lnnmpc.train import schedule


def _counted_steps(iterations: int, per_iteration: int, episode_length: int) -> int:
    """The loop's own rule, one iteration at a time: an environment at its episode's end resets instead of stepping."""
    t = steps = 0
    for _ in range(iterations):
        if t == episode_length:
            t = 0
        else:
            t, steps = t + 1, steps + per_iteration
    return steps


CASES = list(itertools.product((1, 2, 6, 32), (1, 3, 7, 500)))


def test_steps_after_and_iterations_for_match_the_iteration_count():
    for per_iteration, episode_length in CASES:
        counted = [_counted_steps(k, per_iteration, episode_length) for k in range(1200)]
        assert [schedule.steps_after(k, per_iteration, episode_length) for k in range(1200)] == counted
        for steps in range(0, counted[-1] + 1, max(1, counted[-1] // 97)):
            k = schedule.iterations_for(steps, per_iteration, episode_length)
            assert counted[k] >= steps and (k == 0 or counted[k - 1] < steps), (steps, per_iteration, episode_length)


def test_chunks_end_the_run_at_its_budget():
    for (per_iteration, episode_length), steps, eval_every in itertools.product(
            CASES, (1, 600, 2200, 2800, 9999), (1, 600, 10_000)):
        seeded = min(steps, 100) // per_iteration
        chunk = schedule.chunk_length(steps, seeded, per_iteration, episode_length, eval_every, max_chunk=50)
        cap = max(1, min(eval_every // per_iteration, 50))
        assert 1 <= chunk <= cap
        end = schedule.final_steps(steps, seeded, chunk, per_iteration, episode_length)
        training = schedule.iterations_for(steps, per_iteration, episode_length) - seeded
        if training <= 0:
            assert chunk == cap and end == _counted_steps(seeded, per_iteration, episode_length)
            continue
        chunks = -(-training // chunk)
        assert chunks == -(-training // cap)  # no more chunks than chunks of the cap would take
        assert end == _counted_steps(seeded + chunks * chunk, per_iteration, episode_length) >= steps
        assert _counted_steps(seeded + (chunks - 1) * chunk, per_iteration, episode_length) < steps
        assert end - steps < chunks * per_iteration  # less than one iteration per chunk past the budget


def test_a_200k_walker_run_ends_at_200k_not_a_chunk_past_it():
    # walker-run, 16 environments per seed, action repeat 2 (32 env steps an iteration), 500-step episodes, seed
    # phase of 5,000 steps (157 iterations), evaluations every 40K: chunks of 1000 iterations (31,936 env steps)
    # used to end at 228,576
    chunk = schedule.chunk_length(200_000, 157, 32, 500, 40_000, 1000)
    assert chunk == 873 and schedule.final_steps(200_000, 157, chunk, 32, 500) == 200_192
