"""L-BFGS with early stopping, shared by every optimisation stage.

Paper Sec. "Implementation": L-BFGS, tolerances 1e-7 (first-order optimality) and 1e-9
(function/parameter change), at most 10 000 iterations.  Ten thousand iterations over a whole
sequence is minutes of CPU, so this runner stops as soon as the loss improves by less than a
relative ``rel_tol`` over a ``patience`` window of outer steps (beyond the paper: early stopping).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch


@dataclass(frozen=True)
class LBFGSConfig:
    # Paper Sec. "Implementation": learning rate (1.0 for part localisation and IK, 0.1 for Stage 2).
    lr: float = 1.0
    # Paper Sec. "Implementation" caps at 10k iterations; early stopping makes that unreachable here.
    max_iterations: int = 10_000
    # inner L-BFGS iterations per outer step (progress/early-stopping granularity)
    iterations_per_step: int = 10
    # Paper Sec. "Implementation": 1e-7 first-order optimality.
    tolerance_grad: float = 1e-7
    # Paper Sec. "Implementation": 1e-9 on function value / parameter change.
    tolerance_change: float = 1e-9
    # Beyond the paper (early stopping): stop when an outer step improves the loss by less than this fraction.
    rel_tol: float = 1e-4
    # L-BFGS memory
    history_size: int = 20


@dataclass
class OptimizationReport:
    iterations: int = 0
    evaluations: int = 0
    initial_loss: float = math.nan
    final_loss: float = math.nan
    seconds: float = 0.0
    stopped: str = ""
    losses: list[float] = field(default_factory=list)


def run_lbfgs(
    params: Sequence[torch.Tensor],
    loss_fn: Callable[[], torch.Tensor],
    config: LBFGSConfig,
    on_step: Callable[[int, float], None] | None = None,
) -> OptimizationReport:
    """Minimise ``loss_fn()`` over ``params`` (leaf tensors with requires_grad) in place.

    on_step(iterations_done, loss) is called after every outer step (progress bars).
    Uses strong-Wolfe line search, so the paper's lr acts as the initial step length.
    """
    import time

    start = time.perf_counter()
    report = OptimizationReport()
    params = [p for p in params if p.requires_grad]
    if not params:
        with torch.no_grad():
            loss = float(loss_fn())
        report.initial_loss = report.final_loss = loss
        report.stopped = "no free parameters"
        return report
    optimizer = torch.optim.LBFGS(
        params,
        lr=config.lr,
        max_iter=config.iterations_per_step,
        # torch's default (1.25 x max_iter) ends a step early when line searches need extra
        # evaluations, which would look like convergence
        max_eval=config.iterations_per_step * 4,
        tolerance_grad=config.tolerance_grad,
        tolerance_change=config.tolerance_change,
        history_size=config.history_size,
        line_search_fn="strong_wolfe",
    )
    evaluations = 0

    def closure() -> torch.Tensor:
        nonlocal evaluations
        evaluations += 1
        optimizer.zero_grad(set_to_none=True)
        loss = loss_fn()
        if not torch.isfinite(loss):
            raise FloatingPointError("optimisation loss became non-finite")
        loss.backward()
        return loss

    with torch.no_grad():
        previous = float(loss_fn())
    report.initial_loss = previous
    report.losses.append(previous)
    iterations = 0
    report.stopped = "max iterations"
    while iterations < config.max_iterations:
        evals_before = evaluations
        optimizer.step(closure)
        state = optimizer.state[params[0]]
        done = int(state.get("n_iter", iterations + config.iterations_per_step))
        # fewer iterations than asked without hitting the evaluation cap = a tolerance test fired
        stalled = done - iterations < config.iterations_per_step and evaluations - evals_before < config.iterations_per_step * 4
        iterations = done
        with torch.no_grad():
            current = float(loss_fn())
        report.losses.append(current)
        if on_step is not None:
            on_step(iterations, current)
        if stalled:
            report.stopped = "converged (tolerance)"
            break
        if previous - current <= config.rel_tol * max(abs(previous), 1e-12):
            report.stopped = "converged (relative improvement)"
            break
        previous = current
    report.iterations = iterations
    report.evaluations = evaluations
    report.final_loss = report.losses[-1]
    report.seconds = time.perf_counter() - start
    return report
