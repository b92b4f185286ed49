"""A constraint solver with a fixed, unrolled iteration count: MJX's Newton/CG solver without its ``while_loop``.

MJX-JAX runs the constraint solver's iterations in a ``lax.while_loop`` whose condition (iteration count and
convergence) is evaluated on the device and read back by the host before every iteration. At the small batches
of RL training this loop overhead, not arithmetic, sets the cost of a physics step (see
``benchmarks/results/README.md``). :func:`unrolled_solve` runs ``m.opt.iterations`` iterations as straight-line
code instead; an iteration whose environment has already converged (same test as MJX: iteration count, cost
improvement or gradient below ``m.opt.tolerance``) keeps its previous iterate through a select, so the iterates
are the ones MJX's loop produces (``tests/test_env_solver.py`` checks this against ``mjx.step``).

It reuses MJX's own iteration pieces (``Context``, line search, constraint and gradient updates) from
``mujoco.mjx._src.solver``, which is private API: the project pins mujoco-mjx 3.17.0, and the test above fails
loudly if a new version changes them. :func:`unrolled_solver` swaps it in for MJX's ``solve`` only while a step
function is being traced, so other users of MJX in the same process are unaffected.
"""

from __future__ import annotations

import contextlib
import threading

import jax
import jax.numpy as jnp
from mujoco import mjx
from mujoco.mjx._src import solver as mjx_solver
from mujoco.mjx._src.types import DisableBit, SolverType

_PATCH_LOCK = threading.RLock()


def _converged(m: mjx.Model, d: mjx.Data, ctx, iteration: int) -> jax.Array:
    """MJX's stopping rule: () bool."""
    improvement = mjx_solver._rescale(m, d, ctx.prev_cost - ctx.cost)
    gradient = mjx_solver._rescale(m, d, jnp.linalg.norm(ctx.grad))
    return (iteration >= m.opt.iterations) | (improvement < m.opt.tolerance) | (gradient < m.opt.tolerance)


def _iterate(m: mjx.Model, d: mjx.Data, ctx):
    """One Newton (or Polak-Ribiere CG) iteration: line search, then new constraint state and search direction."""
    ctx = mjx_solver._linesearch(m, d, ctx)
    prev_grad, prev_mgrad = ctx.grad, ctx.Mgrad
    ctx = mjx_solver._update_constraint(m, d, ctx)
    ctx = mjx_solver._update_gradient(m, d, ctx)
    if m.opt.solver == SolverType.NEWTON:
        search = -ctx.Mgrad
    else:
        beta = jnp.dot(ctx.grad, ctx.Mgrad - prev_mgrad) / jnp.maximum(1e-15, jnp.dot(prev_grad, prev_mgrad))
        search = -ctx.Mgrad + jnp.maximum(0.0, beta) * ctx.search
    return ctx.replace(search=search, solver_niter=ctx.solver_niter + 1)


def unrolled_solve(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Drop-in for ``mujoco.mjx._src.solver.solve`` with ``m.opt.iterations`` unrolled iterations."""
    qacc = d.qacc_smooth
    if not m.opt.disableflags & DisableBit.WARMSTART:
        warm = mjx_solver.Context.create(m, d.replace(qacc=d.qacc_warmstart), grad=False)
        smooth = mjx_solver.Context.create(m, d.replace(qacc=d.qacc_smooth), grad=False)
        qacc = jnp.where(warm.cost < smooth.cost, d.qacc_warmstart, d.qacc_smooth)
    d = d.replace(qacc=qacc)
    ctx = mjx_solver.Context.create(m, d)
    for iteration in range(m.opt.iterations):
        if iteration == 0:
            ctx = _iterate(m, d, ctx)  # MJX always takes the first iteration
            continue
        done = _converged(m, d, ctx, iteration)
        stepped = _iterate(m, d, ctx)
        ctx = jax.tree_util.tree_map(lambda old, new, done=done: jnp.where(done, old, new), ctx, stepped)
    return d.tree_replace(
        {"qfrc_constraint": ctx.qfrc_constraint, "qacc": ctx.qacc, "_impl.efc_force": ctx.efc_force}
    )


@contextlib.contextmanager
def unrolled_solver():
    """While active, MJX's forward dynamics (also inside RK4) use :func:`unrolled_solve`. Trace inside it."""
    with _PATCH_LOCK:
        original = mjx_solver.solve
        mjx_solver.solve = unrolled_solve
        try:
            yield
        finally:
            mjx_solver.solve = original
