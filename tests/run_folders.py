"""Fake run folders for the tests of lnnmpc.experiments and the batch scripts: a run's config.json, eval.csv,
checkpoints and evaluation files, written as the trainer and `cli eval` lay them out (no training)."""

import os

from lnnmpc.train import runfolder


def write_rows(path, rows):
    """A CSV file of ``rows`` (dicts; the first one's keys are the header) written as the trainer writes its CSVs
    (:func:`lnnmpc.train.runfolder.write_csv`), its folder made as needed."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    runfolder.write_csv(path, list(rows[0]), rows)


def fake_run(folder, last_step, checkpoint=True, returns=None, eval_name=None):
    """A run folder with config.json, eval.csv up to ``last_step`` and optionally a checkpoint at it."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "config.json"), "w") as f:
        f.write('{"config": {}}')
    write_rows(os.path.join(folder, "eval.csv"), [{"env_step": s, "seed": 0, "episode": 0, "return": 1.0}
                                                  for s in (10_000, last_step)])
    if checkpoint:
        os.makedirs(os.path.join(folder, "checkpoints", str(last_step)))
    if returns is not None:
        write_rows(os.path.join(folder, "evals", eval_name),
                   [{"env_step": last_step, "seed": s, "episode": e, "return": returns[s][e]}
                    for s in range(len(returns)) for e in range(len(returns[0]))])
