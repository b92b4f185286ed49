"""Command line of the trainer (the Makefile's ``train``, ``eval``, ``video`` and ``report`` targets call it).

    python -m lnnmpc.train.cli train --task walker-run --seeds 4 --steps 200000 --obs "noise=0.1,flicker=0.2"
    python -m lnnmpc.train.cli train --resume runs/walker-run/tdmpc2/20260101-120000-noise0.1-flicker0.2
    python -m lnnmpc.train.cli train --task walker-run --agent cfc-zp-det --set lambda_=0 --check  # print only
    python -m lnnmpc.train.cli train --recipe sparse --seeds 3     # a task's measured best settings (recipes.py)
    python -m lnnmpc.train.cli recipes                             # list the recipes and what they measured
    python -m lnnmpc.train.cli eval RUN [--obs noise=0.3] [--episodes 10] [--backend mjx|dm_control] [--actor prior]
    python -m lnnmpc.train.cli eval RUN --planner iterations=12 --planner plan_horizon=5  # other MPPI settings
    python -m lnnmpc.train.cli video RUN [--out episode.gif] [--episodes 50 --falls-below 400]
    python -m lnnmpc.train.cli report RUN            # redraw curve.png and summary.md

``train`` without a subcommand name also works (``python -m lnnmpc.train.cli --task ...``). Every option maps to
a field of :class:`lnnmpc.train.config.TrainConfig`; ``--set KEY=VALUE`` (repeatable) sets agent
hyperparameters (``make_agent(..., overrides=...)``). Exit status: 0 done, 2 invalid configuration (before
anything is compiled), 3 training diverged (NaN/Inf), 130 stopped by Ctrl-C after saving a checkpoint.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback

from lnnmpc import envs
from lnnmpc.agents.registry import AGENTS
from lnnmpc.train.config import ConfigError, TrainConfig, obs_tag, parse_overrides
from lnnmpc.train.recipes import RECIPES, describe_recipes, recipe_departures, recipe_values

EXIT_CONFIG, EXIT_DIVERGED, EXIT_INTERRUPTED = 2, 3, 130


def _train_parser(sub) -> None:
    p = sub.add_parser("train", help="train (or resume) a run", argument_default=argparse.SUPPRESS,
                       description="Train an agent on one task for several seeds at once; write a run folder.")
    p.add_argument("--task", help=f"one of: {', '.join(envs.TASKS)}")
    p.add_argument("--recipe", help=f"start from a recipe's settings, one of: {', '.join(RECIPES)} (the options "
                   "given win; `recipes` lists them)")
    p.add_argument("--agent", help=f"one of: {', '.join(AGENTS)} (default tdmpc2; `make train` defaults to cfc-zp-det)")
    p.add_argument("--seeds", type=int, help="independent seeds trained together (default 1)")
    p.add_argument("--steps", type=int, help="environment steps per seed (default 200000)")
    p.add_argument("--envs", type=int, help="environments per seed (default 1)")
    p.add_argument("--obs", help='training corruptions, e.g. "noise=0.1,flicker=0.2,delay=3,remove_vel=1"')
    p.add_argument("--eval-obs", help="evaluation corruptions (default: same as --obs)")
    p.add_argument("--model-size", type=int, help="TD-MPC2 size in millions of parameters: 1 or 5 (default 5)")
    p.add_argument("--seed-steps", type=int, help="random-action environment steps first (default 5000)")
    p.add_argument("--eval-every", type=int, help="environment steps between evaluations (default 10000)")
    p.add_argument("--eval-episodes", type=int, help="evaluation episodes per seed (default 10)")
    p.add_argument("--eval-prior", action="store_true",
                   help="every evaluation also plays its episodes with the policy prior acting alone (no MPPI): "
                        "eval.csv's prior_return")
    p.add_argument("--eval-policies", action="store_true",
                   help="every evaluation also writes the policy it evaluated to policies/policy-<env step>.npz "
                        "(eval/video/analyses --checkpoint STEP replay it without checkpoints)")
    p.add_argument("--explore-noise-beta", type=float,
                   help="exploration noise colored over each episode with power spectrum 1/f^BETA (1 pink, 2 red) "
                        "in place of the planner's white noise (default: white, drawn every step)")
    p.add_argument("--seed-noise-beta", type=float,
                   help="the seed phase acts with noise colored over each episode, spectrum 1/f^BETA, clipped to "
                        "[-1, 1] (default: uniform random actions)")
    p.add_argument("--checkpoint-every", type=int, help="environment steps between checkpoints (default 10000)")
    p.add_argument("--keep-checkpoints", type=int, help="newest checkpoints kept (default 3)")
    p.add_argument("--batch-size", type=int, help="sequences per update (default 256)")
    p.add_argument("--updates-per-step", type=int,
                   help="updates per agent step, the update-to-data ratio (default 1, TD-MPC2's)")
    p.add_argument("--action-repeat", type=int,
                   help="control steps per agent step, rewards summed (default 2, TD-MPC2's on dm_control)")
    p.add_argument("--physics", help=f"one of: {', '.join(envs.PROFILES)} (default fast)")
    p.add_argument("--seed", type=int, help="master seed (default 0)")
    p.add_argument("--small", action="store_true", help="tiny networks and planner (CPU smoke runs)")
    p.add_argument("--replay-capacity", type=int, help="replay slots per environment (default: from --steps)")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                   help="agent hyperparameter override, repeatable (e.g. --set plan_horizon=5)")
    p.add_argument("--devices", type=int, help="devices to shard the seeds over (default: all that divide --seeds)")
    p.add_argument("--runs-dir", help="parent of new run folders (default runs)")
    p.add_argument("--name", help="run folder suffix (default: the corruption tag, e.g. noise0.1)")
    p.add_argument("--out", help="exact run folder (an existing one with checkpoints is resumed)")
    p.add_argument("--resume", help="run folder to continue (its config.json; --steps may extend it)")
    p.add_argument("--tensorboard", action="store_true", help="also write TensorBoard scalars (tensorboardX)")
    p.add_argument("--wandb", metavar="PROJECT",
                   help="also log to this Weights & Biases project (WANDB_MODE=offline: no network)")
    p.add_argument("--compile-cache", help='XLA compilation cache folder ("" turns it off)')
    p.add_argument("--compile-ahead", choices=("auto", "on", "off"),
                   help="compile the run's programs in parallel before training (default auto: with >= 4 cores)")
    _deterministic_option(p, "two launches of one command on an H100 then replayed each other bit for bit, also "
                             "across machines (RESULTS.md [93], [94]); 1.2-1.3 x the time per step there [94]")
    p.add_argument("--check", action="store_true",
                   help="validate the whole configuration (environments, agent, overrides, resume), print what "
                        "would run, write and compile nothing")


def _deterministic_option(p, measured: str) -> None:
    p.add_argument("--deterministic", action="store_true",
                   help="compile under XLA's deterministic GPU ops (XLA_FLAGS=--xla_gpu_deterministic_ops=true, set "
                        f"before JAX starts its backend): {measured}; no effect on the CPU")


def _eval_parser(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a run's checkpoint (or policy.npz) under any corruption, on MJX "
                                    "or dm_control")
    p.add_argument("run", help="run folder")
    p.add_argument("--obs", default=None, help="corruptions (default: the run's evaluation corruptions)")
    p.add_argument("--episodes", type=int, default=10, help="episodes per seed")
    p.add_argument("--backend", default="mjx", help="mjx or dm_control (the original simulator, CPU)")
    p.add_argument("--checkpoint", type=int, default=None,
                   help="environment step of a checkpoint, of policy.npz or of an evaluation's policy in "
                        "policies/ (default the newest)")
    p.add_argument("--seed", type=int, default=0, help="the episodes' seed (default 0): evaluations with one seed "
                   "play the same episodes, to compare episode by episode (python -m lnnmpc.train.paired)")
    p.add_argument("--out", default=None, help="CSV path (default <run>/evals/<backend>-<obs>-<step>.csv)")
    p.add_argument("--actor", default="planner",
                   help="planner (MPPI, as training evaluates) or prior (the policy prior alone, no planning; "
                        "CSV <backend>-prior-<obs>-<step>.csv)")
    p.add_argument("--planner", dest="planner", action="append", metavar="KEY=VALUE", default=[],
                   help="plan with another MPPI setting than the run trained with, repeatable (e.g. --planner "
                        "iterations=12 --planner plan_horizon=5; planner keys only)")
    _deterministic_option(p, "the evaluation's sums in a fixed order, so that it replays on a GPU")


def _video_parser(sub) -> None:
    p = sub.add_parser("video", help="render one evaluation episode (dm_control, MuJoCo renderer) to MP4/GIF")
    p.add_argument("run", help="run folder")
    p.add_argument("--out", default=None, help="video path, .mp4 or .gif (default <run>/videos/<step>.mp4)")
    p.add_argument("--obs", default=None, help="corruptions (default: the run's evaluation corruptions)")
    p.add_argument("--checkpoint", type=int, default=None)
    p.add_argument("--seed-index", type=int, default=0, help="which trained seed's policy")
    p.add_argument("--episode-seed", type=int, default=0,
                   help="episode e is the one `eval --backend dm_control --seed EPISODE_SEED` scores as e")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--max-steps", type=int, default=None, help="cut the episode after this many agent steps")
    p.add_argument("--episodes", type=int, default=1,
                   help="film this many episodes at once (initial states episode-seed + e) into a folder, "
                        "--out or <run>/videos/<step>/, as episode-<e>.mp4")
    p.add_argument("--falls-below", type=float, default=None,
                   help="with --episodes: keep only the films of episodes whose return ends below this")
    p.add_argument("--actor", default="planner",
                   help="planner (MPPI) or prior (the policy prior alone; default file <run>/videos/<step>-prior.mp4)")
    _deterministic_option(p, "the planner's sums in a fixed order, so that a film replays on a GPU")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m lnnmpc.train.cli", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    _train_parser(sub)
    _eval_parser(sub)
    _video_parser(sub)
    sub.add_parser("report", help="redraw curve.png and summary.md").add_argument("run")
    sub.add_parser("recipes", help="list the recipes (--recipe NAME): their settings and what they measured")
    return parser


def _config_values(args: argparse.Namespace) -> dict:
    values = {k: v for k, v in vars(args).items() if k not in ("command", "resume", "check")}
    if "overrides" in values:
        values["overrides"] = values["overrides"] or []
    return values


def run_train(args: argparse.Namespace) -> str:
    """The ``train`` command: a new run (from its options, a recipe's completed by them) or a resumed one (its
    config.json, the options given overriding it), trained, or with ``--check`` only validated and described;
    returns the run folder."""
    from lnnmpc.train import runfolder
    from lnnmpc.train.setup import validate
    from lnnmpc.train.trainer import train

    values = _config_values(args)
    resume, steps, config = getattr(args, "resume", None), None, None
    if "recipe" in values:
        if resume:
            raise ConfigError("--recipe starts a new run; a resumed run keeps the settings its config.json recorded")
        recipe = values.pop("recipe")
        values = recipe_values(recipe, values)
        sys.stderr.write(recipe_departures(recipe, values))
    if resume:
        saved = runfolder.saved_config(resume)
        steps = values.pop("steps", None)
        config = TrainConfig.from_dict({**saved.to_dict(), **values}) if values else None
    elif "task" not in values:
        raise ConfigError(f"--task is required (one of: {', '.join(envs.TASKS)}), or --resume RUN")
    else:
        config = TrainConfig(**values)
    if getattr(args, "check", False):
        setup = validate(config, resume=resume, steps=steps, create=False)
        sys.stdout.write(describe_setup(setup))
        return setup.run
    return train(config, resume=resume, steps=steps)


def describe_setup(setup) -> str:
    """What ``train --check`` prints: the run folder, whether it resumes, and the resolved settings."""
    c, loop = setup.config, setup.loop
    start = (f"resumes at the checkpoint of {setup.resume_step:,} env steps" if setup.resume_step is not None
             else "new run")
    overrides = ", ".join(f"{k}={v}" for k, v in sorted(c.overrides.items())) or "none"
    noise = ("white, drawn every step" if c.explore_noise_beta is None
             else f"colored over each episode, spectrum 1/f^{c.explore_noise_beta:g}")
    seed_actions = ("uniform random actions" if c.seed_noise_beta is None
                    else f"colored noise over each episode, spectrum 1/f^{c.seed_noise_beta:g}, clipped")
    floor = getattr(getattr(loop.agent.config, "planner", None), "explore_min_std", 0.0)
    noise += f", scaled by the planner's std (at least {floor:g})" if floor else ", scaled by the planner's std"
    return (f"OK: {setup.run} ({start})\n"
            f"  {c.task}, {c.agent}, {c.seeds} seed(s) x {c.envs} env(s), {c.steps:,} env steps, "
            f"obs {obs_tag(c.obs)}, eval obs {obs_tag(c.eval_obs)}\n"
            f"  agent overrides: {overrides}\n"
            f"  exploration noise in training: {noise}\n"
            f"  seed phase: {c.seed_steps:,} env steps of {seed_actions}\n"
            f"  evaluation every {c.eval_every:,} env steps, {c.eval_episodes} episode(s) per seed"
            f"{', also with the policy prior alone (prior_return)' if c.eval_prior else ''}"
            f"{', each policy kept in policies/' if c.eval_policies else ''}\n"
            f"  chunk {setup.chunk} iterations of {setup.per_iteration} env steps (ends at "
            f"{setup.final_env_steps:,} env steps), replay "
            f"{loop.config.replay_capacity:,} per env, batch {loop.config.batch_size}, "
            f"{loop.config.updates_per_step} update(s) per agent step, action repeat {loop.env.action_repeat}, "
            f"{setup.num_devices} device(s)"
            f"{', XLA deterministic GPU ops' if c.deterministic else ''}\n")


def run_command(args: argparse.Namespace) -> None:
    if args.command == "train":
        run_train(args)
    elif args.command == "recipes":
        sys.stdout.write(describe_recipes())
    elif args.command in ("eval", "video"):
        from lnnmpc.train.setup import enable_deterministic_ops

        enable_deterministic_ops(args.deterministic)  # before anything starts JAX's backend
        _evaluate_or_film(args)
    else:
        from lnnmpc.train.report import write_reports

        write_reports(args.run)
        sys.stdout.write(f"wrote {os.path.join(args.run, 'summary.md')} and curve.png\n")


def _evaluate_or_film(args: argparse.Namespace) -> None:
    if args.command == "eval":
        os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no OpenGL to step (no GLFW warnings)
        from lnnmpc.train.evaluate import evaluate

        evaluate(args.run, obs=args.obs, episodes=args.episodes, backend=args.backend, checkpoint=args.checkpoint,
                 seed=args.seed, out=args.out, actor=args.actor, planner=parse_overrides(args.planner, "--planner"))
    else:
        os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen OpenGL without a display; before dm_control loads
        from lnnmpc.train.video import record, record_episodes

        options = dict(out=args.out, obs=args.obs, checkpoint=args.checkpoint, seed_index=args.seed_index,
                       episode_seed=args.episode_seed, width=args.width, height=args.height, max_steps=args.max_steps,
                       actor=args.actor)
        if args.episodes == 1 and args.falls_below is None:
            record(args.run, **options)
        else:
            record_episodes(args.run, episodes=args.episodes, below=args.falls_below, **options)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0].startswith("--") and argv[0] not in ("--help", "-h"):
        argv = ["train", *argv]
    args = build_parser().parse_args(argv)
    from lnnmpc.train.trainer import TrainingDiverged

    try:
        run_command(args)
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        exit_now(EXIT_CONFIG)
    except TrainingDiverged as error:
        sys.stderr.write(f"\nerror: {error}\n")
        exit_now(EXIT_DIVERGED)
    except KeyboardInterrupt:
        exit_now(EXIT_INTERRUPTED)
    except Exception:  # a crash: its traceback, then no wait for background compilations either
        if not _compiling():
            raise
        traceback.print_exc()
        exit_now(1)


def _compiling() -> int:
    """How many programs still compile in the background (0 where the trainer's modules were never imported)."""
    sharding = sys.modules.get("lnnmpc.train.sharding")
    return sharding.pending_compilations() if sharding is not None else 0


def exit_now(code: int) -> None:
    """Exits with ``code``. Where programs still compile in the background (the trainer's evaluation, compiled
    while the first chunks train), Python would join their threads first, up to a minute or more on a GPU after
    the checkpoint is saved: then the process leaves at once (``os._exit``, the standard streams flushed), as
    nothing of the run is left unwritten by this point."""
    pending = _compiling()
    if pending:
        sys.stderr.write(f"(not waiting for {pending} program(s) still compiling in the background)\n")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    main()
