"""A warm worker process that runs the staged solver (``staged_solver.solve``) beside the caller.

Why a process and not a thread: the staged solver is thousands of small torch calls driven from
Python, so two solves on two threads share one interpreter lock and run one after the other, with
lock hand-over on top.  Measured on the 2-core CPU (the demo's 8 s walk, 40 markers): one bootstrap
start 18.5 s alone; two starts on two threads 50.2 s wall, slower than running them in turn.  A
steady-state stream beside a background lock upgrade on a thread loses its frame rate the same way.
In a worker process each solve has its own interpreter and the second core does the work.

The worker is started ("spawn": a fresh interpreter, no inherited locks or thread pools) when the
pool is built, so its imports (~3-5 s) are paid before the first job, not inside it.  The body models
go over once, at start-up.  Jobs and results travel as pickles between this process and its own
child (never data from outside the program).  A job is cancelled by its id: the worker's progress
hook checks a shared counter at every stage and optimiser step and raises ``SolveCancelled``.
The worker ends itself when its parent is gone (killed without a chance to shut the pool down).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from concurrent.futures import BrokenExecutor, Future, ProcessPoolExecutor

from uuomocap.solver_core.staged_solver import SolverProgress


class SolveCancelled(RuntimeError):
    """The job was cancelled while it ran (its result is no longer wanted)."""


# Ids of jobs cancelled one by one, in slots by id modulo this (a job is cancelled when its slot
# holds its id; far more slots than jobs ever queue at once).
_CANCEL_SLOTS = 64


class _CancelledBelow(SolverProgress):
    """Raises ``SolveCancelled`` once the caller cancelled this job, or every job up to its id."""

    def __init__(self, job_id: int, cancelled_upto, cancelled_ids):
        self.job_id, self.cancelled_upto, self.cancelled_ids = job_id, cancelled_upto, cancelled_ids

    def check(self) -> None:
        if self.cancelled_upto.value >= self.job_id or self.cancelled_ids[self.job_id % _CANCEL_SLOTS] == self.job_id:
            raise SolveCancelled(f"worker job #{self.job_id} cancelled")

    def stage_start(self, name: str, detail: str = "") -> None:
        self.check()

    def stage_step(self, name: str, iterations: int, loss: float) -> None:
        self.check()


# The worker process's state, set once by its initializer (per child process; the parent never
# touches it).
_worker_state: dict = {}


def _exit_with_parent(parent_pid: int, period_s: float = 1.0) -> None:
    """End this process once its parent is gone.  A parent killed hard (SIGKILL, a crash) cannot
    shut the pool down, and the worker would otherwise live on, finishing a 30-60 s job and then
    sitting on ~400 MB (seen: a killed script's worker still alive minutes later)."""
    while True:
        time.sleep(period_s)
        if os.getppid() != parent_pid:
            os._exit(0)


def _init_worker(model, chamfer_model, cancelled_upto, cancelled_ids, parent_pid) -> None:
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), name="exit-with-parent", daemon=True).start()
    import torch
    from threadpoolctl import threadpool_limits

    from uuomocap.solver_core.staged_solver import preload_lazy_imports

    torch.set_num_threads(1)  # one core per solve: the caller uses the other
    threadpool_limits(1, user_api="blas")
    preload_lazy_imports()
    _worker_state.update(model=model, chamfer_model=chamfer_model, cancelled_upto=cancelled_upto, cancelled_ids=cancelled_ids,
                         cache={})


def _ready() -> int:
    return os.getpid() if _worker_state else 0


def _run_solve(job_id: int, markers, visible, rate_hz, up_axis, prior, shape, config, after=None):
    from uuomocap.solver_core.staged_solver import solve

    s = _worker_state
    res = solve(markers, visible, rate_hz, up_axis, prior, shape, s["model"], s["chamfer_model"], config,
                progress=_CancelledBelow(job_id, s["cancelled_upto"], s["cancelled_ids"]))
    if after is None:
        return res
    fn, args = after
    return res, fn(res, s, *args)


def _run_call(job_id: int, fn, args):
    s = _worker_state
    return fn(s, _CancelledBelow(job_id, s["cancelled_upto"], s["cancelled_ids"]).check, *args)


class StagedSolveWorker:
    """One warm worker process running ``staged_solver.solve`` jobs in submission order.

    model / chamfer_model: the body models every job uses (sent to the worker once).
    ``submit(...)`` takes ``solve``'s data arguments and config and returns (job id, Future);
    ``cancel_upto(job_id)`` cancels that job and every earlier one; ``close()`` ends the worker.
    """

    def __init__(self, model, chamfer_model=None):
        ctx = mp.get_context("spawn")
        self._cancelled_upto = ctx.Value("q", 0, lock=False)
        self._cancelled_ids = ctx.Array("q", _CANCEL_SLOTS, lock=False)
        self._next_id = 0
        self.broken = False
        self._pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker,
                                         initargs=(model, chamfer_model or model, self._cancelled_upto, self._cancelled_ids, os.getpid()))
        self.pid: int | None = None  # the worker's process id, once ready
        self._warm = self._pool.submit(_ready)  # starts the process and its imports now

    def ready(self, timeout: float | None = None) -> bool:
        """Wait up to timeout seconds for the worker's start-up; whether it is ready."""
        try:
            self.pid = self._warm.result(timeout) or None
            return self.pid is not None
        except TimeoutError:
            return False
        except BrokenExecutor:  # could not start (the caller falls back to threads)
            self.broken = True
            return False

    def submit(self, markers, visible, rate_hz, up_axis, prior, shape, config, after=None) -> tuple[int, Future]:
        """(job id, Future of the SolveResult).  A worker that died or could not start gives a
        Future holding ``BrokenExecutor`` (and ``broken`` is True from then on).

        after: optional (function, args) run in the worker on the result, as
        ``function(result, worker_state, *args)`` (worker_state: the models and a ``cache`` dict
        that lives as long as the worker); the Future then holds (result, its return value).
        The function must be importable by name (it travels as a reference)."""
        return self._submit(_run_solve, markers, visible, rate_hz, up_axis, prior, shape, config, after)

    def call(self, fn, *args) -> tuple[int, Future]:
        """(job id, Future of ``fn(worker_state, check, *args)``) run in the worker after the jobs
        before it: worker_state holds the models and a ``cache`` dict that lives as long as the
        worker; ``check()`` raises ``SolveCancelled`` once the job is cancelled (call it often).
        fn must be importable by name.  A dead worker gives a Future holding ``BrokenExecutor``."""
        return self._submit(_run_call, fn, args)

    def _submit(self, runner, *args) -> tuple[int, Future]:
        self._next_id += 1
        try:
            return self._next_id, self._pool.submit(runner, self._next_id, *args)
        except BrokenExecutor as exc:
            self.broken = True
            failed: Future = Future()
            failed.set_exception(exc)
            return self._next_id, failed

    def cancel(self, job_id: int) -> None:
        """Cancel this one job (the jobs before and after it go on)."""
        self._cancelled_ids[int(job_id) % _CANCEL_SLOTS] = int(job_id)

    def cancel_upto(self, job_id: int) -> None:
        self._cancelled_upto.value = max(self._cancelled_upto.value, int(job_id))

    def close(self) -> None:
        """Cancel every job and wait for the worker to end: a running solve stops at its next
        optimiser step.  (Not waiting left the pool's wake-up pipe closed under its manager
        thread: "OSError: Bad file descriptor" at every solver node's exit.)"""
        self.cancel_upto(self._next_id)
        self._pool.shutdown(wait=True, cancel_futures=True)
