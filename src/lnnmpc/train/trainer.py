"""``lnnmpc.train(config)``: the whole training schedule of SPEC §1 for several seeds, with a run folder.

    import lnnmpc
    run = lnnmpc.train(lnnmpc.TrainConfig(task="cartpole-swingup", seeds=4, steps=100_000, obs="noise=0.1"))
    run = lnnmpc.train(resume=run, steps=200_000)          # extend a run (or continue it exactly: no steps)

Order of work: the configuration is validated completely (:func:`lnnmpc.train.setup.validate`: environments and
agent are built, the run folder is checked for write access, a resumed checkpoint is checked against the
configuration and the state layout) before anything is compiled. Then: seed phase, update burst, training chunks; an
evaluation every ``eval_every`` environment steps, a checkpoint every ``checkpoint_every`` (at the first chunk
boundary past each multiple), at the end, and on Ctrl-C / SIGTERM (after the running chunk; a second Ctrl-C aborts
at once). The chunks are of equal length, sized so that the last one ends at the budget
(:mod:`lnnmpc.train.schedule`). Checkpoints hold the whole state and the host's counters, and the chunk schedule
depends only on the configuration, so a resumed run computes what the uninterrupted run would have: bit for bit on
the CPU, up to the round-off by which two GPU launches of one command can part (experiments/RESULTS.md [92]). An
extended budget resizes the chunks from the resume on: the training is the same (it does not depend on where chunks
end), the evaluations and checkpoints may fall at other steps than in a run started with that budget.

``timing.csv`` gives the wall seconds of each phase: ``startup`` (the process before the run's clock: Python,
imports, devices, the checks above, restoring a checkpoint; Linux only), ``compile`` (the programs, in parallel
threads, where ``compile_ahead``; a second row for the training chunk's rest, which compiles while the seed phase
and update burst run; the evaluation's finishes while the first chunks run; ``compile.csv`` gives each program's
seconds; where not compiled ahead, two rows after the seed phase: the training chunk's lowering, then its
compilation), ``initialise`` (the new state; its compilation too where not compiled ahead), ``seed_phase``,
``update_burst``, ``train_chunk``, ``evaluate``, ``checkpoint``; their sum is the process's time up to its last
checkpoint, less the host's bookkeeping between chunks.

A NaN or Inf in a loss metric or in the agent's parameters stops the run with :class:`TrainingDiverged` naming the
environment step, seed and metric; the newest checkpoint (written before the bad chunk) is kept as it is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from lnnmpc.train import report, runfolder
from lnnmpc.train.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from lnnmpc.train.compat import agent_config_json
from lnnmpc.train.config import TrainConfig
from lnnmpc.train.guard import StopRequest, all_finite, first_non_finite
from lnnmpc.train.policy_file import save_policy, save_policy_snapshot
from lnnmpc.train.provenance import process_seconds, provenance_entry
from lnnmpc.train.setup import Setup, enable_compile_cache, validate
from lnnmpc.train.sharding import AheadOfTime, SeedPlacement, compile_ahead

TIMING_FILE = "timing.csv"  # wall seconds of each phase (kept apart from train.csv, which is deterministic)
COMPILE_FILE = "compile.csv"  # seconds to lower and compile each program compiled ahead (and the chunk)
# eval.csv's columns after env_step, seed and episode, in order (TrainingLoop.evaluate_logged; prior_return only
# with eval_prior)
EVAL_COLUMNS = ("return", "effective_rank", "prior_return")


def evaluation_key_chain(seed: int) -> jax.Array:
    """The key a run with master seed ``seed`` splits its evaluations' keys from, one per evaluation in turn
    (:func:`next_evaluation_key`)."""
    return jax.random.key(seed + 10_000)


def next_evaluation_key(chain: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(the chain for the evaluations after this one, this evaluation's key): split once from ``chain``; the key is
    then split into the run's seeds."""
    chain, key = jax.random.split(chain)
    return chain, key


class TrainingDiverged(RuntimeError):
    """A loss or parameter became NaN/Inf; the message names the environment step, seed and metric."""


def train(config: TrainConfig | None = None, *, resume: str | None = None, steps: int | None = None) -> str:
    """Trains (or resumes, see :func:`validate`) and returns the run folder.

    Raises ConfigError before compiling for a bad configuration or a run folder that another process is training
    in (:func:`runfolder.hold_run`), :class:`TrainingDiverged` on NaN/Inf, and KeyboardInterrupt after saving a
    checkpoint on Ctrl-C.
    """
    setup = validate(config, resume=resume, steps=steps)
    with runfolder.hold_run(setup.run):
        enable_compile_cache(setup.config.compile_cache)
        return _Run(setup).execute()


class _Run:
    """Host-side driver of one run (state between chunks, counters, files)."""

    def __init__(self, setup: Setup):
        self.setup, self.config, self.loop, self.run = setup, setup.config, setup.loop, setup.run
        self.placement = SeedPlacement(setup.num_devices)
        compile_ = self.placement.compile
        self.init = compile_(self.loop.init)
        self.evaluate = compile_(self.loop.evaluate_logged)
        self.finite = compile_(all_finite)
        self._chunk_fns = {}
        self.counters = {"env_steps": 0, "next_eval": self.config.eval_every, "last_eval": -1,
                         "next_checkpoint": self.config.checkpoint_every, "last_checkpoint": -1, "seeded": False,
                         "eval_key": None, "train_seconds": 0.0}
        self.progress = report.Progress(self.config.steps)
        self.loggers = ([report.ScalarLogger(self.run)] if self.config.tensorboard else []) + (
            [report.WandbLogger(self.run, self.config.wandb, self.config.to_dict())]
            if self.config.wandb else [])

    def _compile_ahead(self, keys: jax.Array, state, initialise: bool) -> None:
        """Compiles the programs the run will call (the training chunk, the seed phase and update burst unless
        done, the state's initialisation if ``initialise``, the parameters' finiteness check, the evaluation) in
        parallel, the training chunk's (the longest to compile) lowered first, and waits for all but the training
        chunk's, which goes on compiling while the state is initialised and the seed phase and update burst run
        (:meth:`_schedule` waits for it before the first chunk, in a second compile row), and the evaluation's,
        which goes on while the first chunks run. compile.csv gets each program's lowering and compilation
        seconds, and when it was ready after this phase began, as each compilation ends.
        ``keys``: (seeds,) keys, placed; ``state``: the training state or its ``placement.abstract`` shapes (the
        programs need its shapes and placement only, so nothing waits for the state to be built)."""
        names = [("train_chunk", self.setup.chunk)]
        seed_iterations = self.setup.seed_iterations
        if not self.counters["seeded"] and seed_iterations:
            names += [("seed_chunk", seed_iterations), ("update_burst", self.setup.burst_updates)]
        jobs = [(name, self._chunk_program(name, length), (state,)) for name, length in names]
        jobs += [("init", self.init, (keys,))] if initialise else []
        jobs += [("finite", self.finite, (state.agent,)), ("evaluate", self.evaluate, (state.agent, keys))]
        labels = [name for name, _, _ in jobs]
        programs = dict(zip(labels, compile_ahead([job[1:] for job in jobs], on_done=self._compile_rows(labels)),
                            strict=True))
        for name in programs.keys() - {"train_chunk", "evaluate"}:  # those two go on compiling
            programs[name].ready()
        self.init, self.finite = programs.get("init", self.init), programs["finite"]
        self.evaluate = programs["evaluate"]  # its first call waits for it
        self._chunk_fns.update({(name, length): programs[name] for name, length in names})

    def _compile_rows(self, names: list[str]):
        """``on_done`` for :func:`compile_ahead` over programs ``names``: appends each program's row to compile.csv
        as its compilation ends (``ready_s`` counted from now)."""
        start, lock, env_step = time.perf_counter(), threading.Lock(), self.counters["env_steps"]

        def written(index: int, program) -> None:  # in the compiling thread
            with lock:
                runfolder.append_csv(os.path.join(self.run, COMPILE_FILE), [{
                    "env_step": env_step, "program": names[index], "lower_s": round(program.lower_s, 4),
                    "compile_s": round(program.compile_s, 4), "ready_s": round(program.done_at - start, 4)}])
        return written

    def _lower_training_chunk(self) -> None:
        """Where nothing was compiled ahead: lowers the training chunk right after the seed phase, before the
        evaluation that may follow traces its program, and compiles it before the first chunk (:meth:`_schedule`,
        a ``compile`` row). Traced before the evaluation, as in :meth:`_compile_ahead` and in a resumed run, the
        chunk is the same program as there and hits the same persistent-cache entry (:func:`compile_ahead`'s
        ``parallel=False`` says why); traced after the evaluation it would be compiled again."""
        key = ("train_chunk", self.setup.chunk)
        if self.counters["env_steps"] >= self.config.steps or isinstance(self._chunk_fns.get(key), AheadOfTime):
            return  # no training chunk to run, or compiled ahead
        with self._timed("compile"):
            self._chunk_fns[key] = compile_ahead([(self.chunk_fn(*key), (self.ts,))], parallel=False,
                                                 on_done=self._compile_rows(["train_chunk"]))[0]

    def _chunk_program(self, name: str, length: int):
        """``loop.<name>(ts, length)`` over seeds, jitted (compiled on the first call)."""
        return self.placement.compile(getattr(self.loop, name), length)

    def chunk_fn(self, name: str, length: int):
        """Compiled ``loop.<name>(ts, length)`` over seeds (cached per length; compiled ahead or on first call)."""
        if (name, length) not in self._chunk_fns:
            self._chunk_fns[name, length] = self._chunk_program(name, length)
        return self._chunk_fns[name, length]

    # ------------------------------------------------------------------------------------ lifecycle
    def execute(self) -> str:
        c = self.config
        runfolder.write_config(self.run, c, {
            "state_signature": self.setup.signature, "agent_config": agent_config_json(self.loop.agent.config),
            "loop": dataclasses.asdict(self.loop.config), "devices": [d.device_kind for d in jax.devices()],
            "num_devices": self.setup.num_devices, "chunk": self.setup.chunk,
            "provenance": runfolder.read_provenance(self.run) + [provenance_entry()]})
        keys = self.placement.put(jax.random.split(jax.random.key(c.seed), c.seeds))
        state = self.placement.abstract(self.setup.state_shapes)  # shapes and placement of the training state
        self.counters["eval_key"] = _key_list(evaluation_key_chain(c.seed))
        resumed = self.setup.resume_step is not None
        if resumed:
            self.ts, self.counters = restore_checkpoint(self.run, self.setup.resume_step, state)
            sys.stderr.write(f"resuming {self.run} at {self.counters['env_steps']:,} env steps\n")
        for name in ("train.csv", "eval.csv", TIMING_FILE, COMPILE_FILE):  # rows after the checkpoint (or all) go
            runfolder.truncate_csv(os.path.join(self.run, name), self.counters["env_steps"] if resumed else -1)
        start, startup = time.perf_counter(), process_seconds()  # the run's clock counts its compilation
        if startup is not None:  # the process before the run's clock: Python, imports, devices, checks, restoring
            self._timing_row("startup", startup, 0)
        if c.compile_ahead == "on" or (c.compile_ahead == "auto" and (os.cpu_count() or 1) >= 4):
            with self._timed("compile"):
                self._compile_ahead(keys, state, initialise=not resumed)
        if not resumed:
            with self._timed("initialise"):  # (its compilation too, where not compiled ahead)
                self.ts = jax.block_until_ready(self.init(keys))
        with StopRequest() as stop:
            try:
                self._schedule(stop)
            finally:
                self.counters["train_seconds"] += time.perf_counter() - start
                for logger in self.loggers:
                    logger.close()
        # the last evaluation plotted the finished run already; summary.md gains the time and the last checkpoint
        report.write_reports(self.run, self.counters, plots=self.counters["last_eval"] != self.counters["env_steps"])
        sys.stderr.write(f"\nrun folder: {self.run}\n")
        return self.run

    def _schedule(self, stop: StopRequest) -> None:
        c, n = self.config, self.counters
        if not n["seeded"]:
            seed_iterations = self.setup.seed_iterations
            if seed_iterations:
                with self._timed("seed_phase") as timed:
                    ts, out = self.chunk_fn("seed_chunk", seed_iterations)(self.ts)
                    rows = self._account(out)
                    timed["env_steps"] = n["env_steps"]
                with self._timed("update_burst"):
                    ts, metrics = self.chunk_fn("update_burst", self.setup.burst_updates)(ts)
                    jax.block_until_ready(ts)
                self._commit(ts, rows, metrics, first_step=None)
            n["seeded"] = True
            self._lower_training_chunk()
            self._after_chunk()
        train = self.chunk_fn("train_chunk", self.setup.chunk)
        if isinstance(train, AheadOfTime) and not train.done():
            with self._timed("compile"):  # the rest of its compilation, which ran beside the seed phase
                train.ready()
        while n["env_steps"] < c.steps:
            if stop.requested:
                self._checkpoint()
                sys.stderr.write(f"\nstopped by {stop.requested} at {n['env_steps']:,} env steps; checkpoint "
                                 f"saved. Continue with: make train RESUME={self.run}\n")
                raise KeyboardInterrupt
            first = n["env_steps"]
            with self._timed("train_chunk") as timed:
                ts, out = train(self.ts)
                rows = self._account(out)
                timed["env_steps"] = n["env_steps"] - first
            self._commit(ts, rows, out, first_step=first)
            self._after_chunk()
        if n["last_eval"] != n["env_steps"]:
            self._evaluate()
        if n["last_checkpoint"] != n["env_steps"]:
            self._checkpoint()
        self.progress.show(n["env_steps"])

    def _after_chunk(self) -> None:
        c, n = self.config, self.counters
        if n["env_steps"] >= n["next_eval"]:
            self._evaluate()
            n["next_eval"] += c.eval_every
        if n["env_steps"] >= n["next_checkpoint"]:
            self._checkpoint()
            n["next_checkpoint"] = (n["env_steps"] // c.checkpoint_every + 1) * c.checkpoint_every
        self.progress.show(n["env_steps"])

    # ---------------------------------------------------------------------------------------- pieces
    def _account(self, out: dict) -> list[dict]:
        """Counts the chunk's environment steps; finished episodes become train.csv rows (with the losses)."""
        returns = np.asarray(out["episode_return"])  # (seeds, iterations, envs), NaN except at episode ends
        terminal = np.isfinite(returns[0, :, 0])
        metrics = {k: np.asarray(v) for k, v in out.items() if k not in ("reward", "episode_return")}
        rows, steps = [], self.counters["env_steps"]
        for i in range(returns.shape[1]):
            if not terminal[i]:
                steps += self.setup.per_iteration
                continue
            for s in range(returns.shape[0]):
                rows.append({"env_step": steps, "seed": s, "episode_return": float(np.mean(returns[s, i])),
                             **{k: float(v[s, i]) for k, v in metrics.items()}})
        self.counters["env_steps"] = steps
        return rows

    def _commit(self, ts, rows: list[dict], metrics: dict, first_step: int | None) -> None:
        """Accepts a chunk's state after checking losses and parameters for NaN/Inf (``first_step``: env step
        before the chunk; None for the update burst after the seed phase)."""
        bad = first_non_finite(metrics)
        finite_params = np.asarray(self.finite(ts.agent))
        if bad is None and not finite_params.all():
            bad = (int(np.argmin(finite_params)), -1, "agent parameters / optimiser state")
        if bad is not None:
            seed, index, metric = bad
            if index < 0:
                where = f"the chunk ending at env step {self.counters['env_steps']:,}"
            elif first_step is None:
                where = f"update {index + 1} of the burst after the seed phase"
            else:
                where = f"env step ~{first_step + (index + 1) * self.setup.per_iteration:,}"
            kept = latest_step(self.run)
            raise TrainingDiverged(
                f"non-finite {metric} (NaN or Inf) at {where}, seed {seed}; training stopped. "
                + (f"The last good checkpoint ({kept:,} env steps) is kept in {self.run}/checkpoints."
                   if kept is not None else "No checkpoint had been written yet."))
        self.ts = ts
        runfolder.append_csv(os.path.join(self.run, "train.csv"), rows)
        for logger in self.loggers:
            logger.train_rows(rows)

    @contextlib.contextmanager
    def _timed(self, phase: str):
        """Appends (env_step at the end, phase, wall seconds, env steps per seed done, their rate) to
        timing.csv; the body may set ``env_steps``. The first call of each compiled program includes compiling."""
        info, start = {"env_steps": 0}, time.perf_counter()
        yield info
        self._timing_row(phase, time.perf_counter() - start, info["env_steps"])

    def _timing_row(self, phase: str, seconds: float, env_steps: int) -> None:
        runfolder.append_csv(os.path.join(self.run, TIMING_FILE), [{
            "env_step": self.counters["env_steps"], "phase": phase, "seconds": round(seconds, 4),
            "env_steps_per_seed": env_steps,
            "env_steps_per_s_all_seeds": round(env_steps * self.config.seeds / max(seconds, 1e-9), 2)}])

    def _evaluate(self) -> None:
        with self._timed("evaluate"):
            self._evaluate_now()

    def _evaluate_now(self) -> None:
        n = self.counters
        eval_key, key = next_evaluation_key(jax.random.wrap_key_data(jnp.asarray(n["eval_key"], jnp.uint32)))
        n["eval_key"], n["last_eval"] = _key_list(eval_key), n["env_steps"]
        keys = self.placement.put(jax.random.split(key, self.config.seeds))
        values = {k: np.asarray(v) for k, v in self.evaluate(self.ts.agent, keys).items()}  # (seeds, episodes)
        columns = [name for name in EVAL_COLUMNS if name in values]
        seeds, episodes = values["return"].shape
        rows = [{"env_step": n["env_steps"], "seed": s, "episode": e,
                 **{name: float(values[name][s, e]) for name in columns}}
                for s in range(seeds) for e in range(episodes)]
        runfolder.append_csv(os.path.join(self.run, "eval.csv"), rows)
        if self.config.eval_policies:  # the evaluated parameters, for analyses of runs back from a GPU
            save_policy_snapshot(self.run, n["env_steps"], self.ts.agent)
        self.progress.last_eval = float(values["return"].mean())
        self.progress.last_prior = float(values["prior_return"].mean()) if "prior_return" in values else np.nan
        for logger in self.loggers:
            logger.eval_rows(rows)
        report.write_reports(self.run, self.counters)

    def _checkpoint(self) -> None:
        with self._timed("checkpoint"):
            self._checkpoint_now()

    def _checkpoint_now(self) -> None:
        n = self.counters
        n["last_checkpoint"] = n["env_steps"]
        save_checkpoint(self.run, n["env_steps"], self.ts, dict(n), keep=self.config.keep_checkpoints)
        save_policy(self.run, n["env_steps"], self.ts.agent)  # the parameters alone, for runs back from a GPU


def _key_list(key: jax.Array) -> list[int]:
    return np.asarray(jax.random.key_data(key)).tolist()
