"""solver: the near-online sliding-window solver (``solver_core.windowed_solver``) as a node.

Inputs: ``markers/raw`` (MarkerFrame; a tracker's fixed-slot output works too: a slot whose
track id changes is a new marker) and ``body/prior`` (BodyPrior, optional: without it the
bootstrap starts from a neutral body).  Output ``body/solved``: a SolvedFrame 'estimate' for every
frame as soon as it is solved, and a 'refined' one once the frame leaves the fixed lag; after a lock
upgrade, a 'revised' one for each frame refined under the old lock (the last ``revise_s`` seconds;
recordings keep it over the refined one; only while the node keeps up).  All carry the current
marker labels.  End of the marker stream flushes every remaining refined frame, then
ends ``body/solved``.

Deterministic in lockstep: a frame only ever uses priors stamped at or before it (the replay's
'solver:body/prior' credit guarantees those arrived), and each solve is single-threaded (the
bootstrap solves its second start in the solver's worker process, each one deterministic; the best
fit wins).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from uuomocap.protocol.messages import SolvedFrame

from .base import Node, Port


@dataclass(frozen=True)
class SolverNodeConfig:
    body_model: str = "open-low"  # open-low, open-full, or a SMPL .pkl/.npz path
    bootstrap_s: float = 3.0  # seconds of markers (+ prior) for the offline bootstrap
    lag_frames: int = 10  # fixed lag of the refined output
    hop_frames: int = 10  # frames finalised per smoothing pass (10: ~1/3 less smoothing work per frame than 5)
    defer_refine_hops: int = 2  # while frames queue up, smoothing waits for up to this many hops, then runs one pass per frame
    estimate_iterations: int | None = None  # None (and smoothness_weight None): the windowed solver's defaults
    smoothness_weight: float | None = None
    publish_estimates: bool = True
    threads: int = 1  # torch intra-op threads (1 = deterministic and leaves a core to the graph)
    # lock upgrades (the staged solver on frames spread over the take, ~30-60 s each time the take
    # grows 1.5x) in the worker process: true for live streams (no stall), false keeps replays deterministic
    upgrade_in_background: bool = False
    # bootstrap starts solved side by side, the second in a worker process (the best marker fit is locked);
    # 1 = only the first, for a machine whose second core the rest of the graph needs at start-up
    bootstrap_starts: int = 2

    def __post_init__(self):
        if (self.bootstrap_s <= 0 or self.lag_frames < 0 or self.hop_frames < 1 or (self.estimate_iterations is not None and self.estimate_iterations < 1) or self.threads < 1
                or self.defer_refine_hops < 1 or self.bootstrap_starts not in (1, 2)):
            raise ValueError("bootstrap_s > 0, lag_frames >= 0, hop_frames >= 1, estimate_iterations >= 1, threads >= 1, "
                             "defer_refine_hops >= 1, bootstrap_starts 1 or 2 are required")


class Solver(Node):
    Config = SolverNodeConfig
    SUBSCRIBES = {
        "markers": Port("markers/raw", types=("MarkerFrame",)),
        "prior": Port("body/prior", types=("BodyPrior",), optional=True),
    }
    PUBLISHES = {"solved": "body/solved"}
    # a bootstrap in progress finishes before the node stops, then the drain (<= DRAIN_MAX_S) and the take's end:
    # beside a live video estimator on 2 cores a bootstrap took 38-42 s and 60 s ended the node by SIGALRM (session 38)
    STOP_TIMEOUT_S = 120
    # stopped mid-take (Ctrl-C on a live graph): solve the frames still queued, then flush the lag
    # (on_stop) - before this the recording lost the last lag frames' refined results and any backlog
    DRAIN_ON_STOP_S = 0.5
    DRAIN_MAX_S = 30.0
    WORKER_START_TIMEOUT_S = 20.0  # setup waits this long for the worker process's imports (a replay waits 30 s for it)

    def setup(self) -> None:
        import torch

        from uuomocap.solver_core.body_model import load_solver_models
        from uuomocap.solver_core.staged_solver import preload_lazy_imports
        from uuomocap.solver_core.windowed_solver import WindowedSolverConfig, start_worker

        torch.set_num_threads(self.config.threads)
        preload_lazy_imports()  # at start-up: the solver is built on the first marker frame
        c = self.config
        self.model, self.chamfer_model = load_solver_models(c.body_model)
        self.solver_config = replace(WindowedSolverConfig(), bootstrap_s=c.bootstrap_s, lag_frames=c.lag_frames, hop_frames=c.hop_frames,
                                     estimate_iterations=c.estimate_iterations, upgrade_in_background=c.upgrade_in_background,
                                     **({} if c.smoothness_weight is None else {"smoothness_weight": c.smoothness_weight}),
                                     **({"bootstrap_alternatives": ()} if c.bootstrap_starts == 1 else {}))
        self.solver, self.rate_hz, self._early_priors = None, 0.0, []
        # the worker process (second bootstrap start, background upgrades) starts now and setup waits
        # for it, as `solve --method uuo-window` and `bench speed` do: a replay starts at once, and in
        # lockstep its first 3 s arrive in under a second - the worker's imports (~3 s) then sat inside
        # the bootstrap (make demo: 12.0 s against 8.0 s).  A live solver is up before the take.
        t0 = time.monotonic()
        self.worker = start_worker(self.model, self.chamfer_model, self.solver_config)
        if self.worker is not None and not self.worker.ready(self.WORKER_START_TIMEOUT_S):  # late or broken: the solver copes (threads)
            self.log.warning("solve worker not ready after %.1f s; the bootstrap may wait for it", time.monotonic() - t0)
        self.log.info("solver: %s, bootstrap %.1fs, lag %d frames", c.body_model, c.bootstrap_s, c.lag_frames)

    def _make_solver(self, msg) -> None:
        from uuomocap.solver_core.windowed_solver import WindowedSolver

        self.rate_hz = float(msg.rate_hz) if msg.rate_hz > 0 else 0.0
        self.solver = WindowedSolver(self.model, self.solver_config, msg.up_axis, self.rate_hz or None, self.chamfer_model,
                                     worker=self.worker)
        self.worker = None  # the solver owns it now
        for row in self._early_priors:
            self.solver.add_prior(*row)
        self._early_priors = []

    def on_prior(self, msg, env) -> None:
        row = (msg.stamp_ns, msg.global_orient, msg.body_pose, msg.betas, msg.valid, msg.camera_frame, msg.confidence)
        if self.solver is None:
            self._early_priors = (self._early_priors + [row])[-512:]
        else:
            self.solver.add_prior(*row)

    def on_markers(self, msg, env) -> None:
        if self.solver is None:
            self._make_solver(msg)
        s = self.solver
        if self.stopping:  # draining after a stop: the take is over, no lock upgrade can pay off
            s.end_upgrades()
        was_locked = s.locked
        # Behind the stream (frames queued, e.g. after the bootstrap): one Gauss-Newton iteration per
        # estimate, and the smoothing passes are deferred (bounded) and spread out.  Lockstep never
        # queues a frame, so it always runs the full budget: deterministic.
        behind = self.input_waiting("markers")
        self.count("behind" if behind else "on_time")
        results = s.push_markers(msg.stamp_ns, msg.positions, msg.visible, msg.track_ids, msg.frame_index,
                                 iterations=1 if behind else None)
        self._publish(results)  # the estimate goes out before the smoothing pass runs
        if s.locked and not was_locked:
            from uuomocap.solver_core.windowed_solver import bootstrap_starts_summary

            starts = bootstrap_starts_summary(s.stats)
            self.log.info("bootstrap done in %.1f s (%d frames estimated%s)", s.stats["bootstrap_seconds"][-1], len(results),
                          f", starts' marker fit {starts}" if starts else "")
        c = self.config
        if not self.input_waiting("markers"):
            self._publish(s.refine_ready())  # on time: every due smoothing pass
        elif s.buffer_sizes()["pending"] >= c.lag_frames + c.defer_refine_hops * c.hop_frames:
            self._publish(s.refine_ready(max_passes=1))  # behind: one pass per frame at most (bounded stall)
        self.counters.update({f"solver_{k}": v for k, v in s.stats.items() if isinstance(v, int)})

    def on_eos(self, port, env) -> None:
        if port != "markers" or self.solver is None:
            return
        self._finish_take()
        self.end_stream("solved")

    def on_stop(self) -> None:
        if self.solver is not None:
            # a stop ends the take at once: no end-of-take lock upgrade (a staged solve, 10-30 s);
            # an end of stream (on_eos) runs it
            self.solver.end_upgrades()
            self._finish_take()

    def _finish_take(self) -> None:
        from uuomocap.solver_core.windowed_solver import take_end_summary

        results = self.solver.flush()
        self._publish(results)
        summary = take_end_summary(self.solver.stats, sum(r.kind == "revised" for r in results))
        if results and summary:  # why the last frames came late
            self.log.info("take end: %s", summary)

    def teardown(self) -> None:
        if self.solver is not None:
            self.solver.close()  # a lock upgrade still running in the worker stops at its next step; the worker ends
        if self.worker is not None:
            self.worker.close()

    def _publish(self, results) -> None:
        if not results:
            return
        faces, bary, parts = self.solver.label_arrays()
        for r in results:
            if r.kind == "estimate" and not self.config.publish_estimates:
                continue
            self.publish("solved", SolvedFrame(
                stamp_ns=int(r.stamp_ns), frame_index=int(r.frame_index), kind=r.kind,
                betas=r.betas.astype(np.float32), poses=r.poses.astype(np.float32), trans=r.trans.astype(np.float32),
                joints=r.joints.astype(np.float32), marker_faces=faces, marker_bary=bary, marker_parts=parts,
                residual_m=float(r.residual_m), rate_hz=self.rate_hz, body_model=self.config.body_model,
            ), int(r.stamp_ns))
            self.count(f"published_{r.kind}")
