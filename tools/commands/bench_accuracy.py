"""``uuomocap bench accuracy``: run every method on the same generated sessions, print the
paper-style tables (rows = methods; m2s / MPJPE / MPJVE / V2V per scenario) and write JSON.

Sessions are generated deterministically from seeds into a cache directory (reused while
the generator version and configuration are unchanged); method outputs are recomputed on
every run.  Scenarios of the ``full`` suite follow the paper: random layouts of 20/30/40/50
markers (nested per seed) x seeds x motions (appendix "Synthetic Marker Placement"), the
three partial-body parts of Table 2 (left leg, right arm, left shoulder), and occlusion
0 / 0.2 % / 1 % with 10-frame hides (appendix "Marker Tracking Loss").  Like the paper,
markers run at 30 Hz.

``--captures FILE[,FILE...]`` runs the methods on real labeled captures instead: each file becomes
a session of its own markers, unlabeled, scored against its labelled fit (``capture_session``;
table "real captures", one scenario per file, ``--seeds`` camera / prior draws each, at the
capture's own rate).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, add_threads_flag, solo_thread_count, torch_threads

FULL_MOTIONS = ("walk", "jump", "arms")
PARTS = ("left_leg", "right_arm", "left_shoulder")
PART_MARKERS = 12
MARKER_COUNTS = (20, 30, 40, 50)
OCCLUSIONS = (0.0, 0.002, 0.01)
# Columns per table: (metric key, header).  Partial tables show the part's joints.
SMOKE_METHODS = ("gt", "video-rr", "oracle-labeled", "uuo", "uuo-window")
FULL_COLUMNS = (("m2s", "m2s"), ("mpjpe", "MPJPE"), ("mpjve", "MPJVE"), ("v2v", "V2V"))
PA_COLUMN = ("pa_mpjpe", "PA-MPJPE")  # --pa-mpjpe: per-frame similarity-aligned MPJPE (a video prior's own accuracy)
PART_COLUMNS = (("m2s", "m2s"), ("part_mpjpe", "MPJPE"), ("part_mpjve", "MPJVE"), ("part_found", "found%"))


# uuo-window's live outputs, kept in its npz beside the recording it is scored as: rows of their own
# (MPJPE / MPJVE, the part's joints on a partial body) so the near-online table comes from this command.
LIVE_OUTPUT_ROWS = (("refined", "uuo-window fixed-lag"), ("estimate", "uuo-window estimate"))


def live_output_metrics(out_npz: Path, gt_npz: Path) -> dict[str, dict]:
    """{row name: metrics} for the fixed-lag refined and the causal estimate frames of a
    uuo-window output (none when the npz has no such keys or a frame has no result)."""
    from uuomocap.protocol.session import read_npz
    from uuomocap.solver_core.metrics import mpjpe, mpjve
    from uuomocap.solver_core.parts import PART_JOINTS

    pred, gt = read_npz(out_npz), read_npz(gt_npz)
    gj, rate = np.asarray(gt["joints"], np.float64), float(np.asarray(gt["mocap_framerate"]))
    part = str(np.asarray(gt["part"])) if "part" in gt else ""
    rows = {}
    for kind, name in LIVE_OUTPUT_ROWS:
        pj = np.asarray(pred.get(f"{kind}_joints", np.zeros(0)), np.float64)
        if pj.shape != gj.shape or not np.isfinite(pj).all():
            continue
        rows[name] = {"mpjpe": mpjpe(pj, gj), "mpjve": mpjve(pj, gj, rate)}
        if part in PART_JOINTS:
            rows[name].update(part_mpjpe=mpjpe(pj, gj, PART_JOINTS[part]), part_mpjve=mpjve(pj, gj, rate, PART_JOINTS[part]))
    return rows


def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "uuomocap" / "bench"


def suite_scenarios(suite: str, seeds: int | None, motions: tuple[str, ...] | None, video: bool,
                    duration_s: float | None = None, only: tuple[str, ...] | None = None):
    """-> list of (table, scenario, [SampleConfig...]).

    duration_s: session length (default 8 s, smoke 2.5 s); only: keep these scenario names."""
    scen = _suite_scenarios(suite, seeds, motions, video, duration_s)
    if only:
        names = [s for _, s, _ in scen]
        unknown = [o for o in only if o not in names]
        if unknown:
            raise UserError(f"unknown scenario(s) {', '.join(map(repr, unknown))} in suite {suite}; "
                            f"scenarios: {', '.join(map(repr, dict.fromkeys(names)))}")
        scen = [x for x in scen if x[1] in only]
    return scen


def _suite_scenarios(suite: str, seeds: int | None, motions: tuple[str, ...] | None, video: bool,
                     duration_s: float | None):
    from uuomocap.synth import SampleConfig

    base = SampleConfig(rate_hz=30.0, duration_s=8.0, video=video, video_size=(320, 240))
    if suite == "smoke":
        base = replace(base, duration_s=duration_s or 2.5)
        return [
            ("smoke", "walk 40", [replace(base, motion="walk", n_markers=40, seed=0)]),
            ("smoke", "jump 30 occl 1%", [replace(base, motion="jump", n_markers=30, occlusion=0.01, seed=1)]),
        ]
    if suite != "full":
        raise UserError(f"unknown suite {suite!r}; use smoke or full")
    if duration_s:
        base = replace(base, duration_s=float(duration_s))
    n_seeds = 10 if seeds is None else seeds
    mots = motions or FULL_MOTIONS
    grid = [(m, s) for m in mots for s in range(n_seeds)]
    out = []
    for n in MARKER_COUNTS:
        out.append(("marker count", f"{n} markers", [replace(base, motion=m, seed=s, n_markers=n) for m, s in grid]))
    for part in PARTS:
        out.append(("partial body", part, [replace(base, motion=m, seed=s, part=part, n_markers=PART_MARKERS)
                                           for m, s in grid]))
    for p in OCCLUSIONS:
        out.append(("occlusion (40 markers)", f"occl {100 * p:g}%",
                    [replace(base, motion=m, seed=s, n_markers=40, occlusion=p) for m, s in grid]))
    # the same hides, each marker back as a new column (an unlabelled export): every column one seen stretch
    out.append(("occlusion (40 markers)", "breaks 1%",
                [replace(base, motion=m, seed=s, n_markers=40, occlusion=0.01, track_breaks=True) for m, s in grid]))
    return out


@dataclass(frozen=True)
class CaptureConfig:
    """A session built from a real labeled capture (``capture_session.make_capture_session``):
    the file, its content hash (the cache key changes with the file) and the camera / prior draw."""

    file: str
    sha1: str
    sample: object  # SampleConfig: seed, prior and video fields

    @property
    def body_model(self) -> str:
        return self.sample.body_model


def capture_scenarios(files: list[str], seeds: int | None, video: bool):
    """One scenario per capture file, ``seeds`` draws of camera and prior each (default 1)."""
    from uuomocap.synth import SampleConfig

    out = []
    for f in files:
        path = Path(f)
        if not path.is_file():
            raise UserError(f"--captures: {f} is not a file")
        sha = hashlib.sha1(path.read_bytes()).hexdigest()[:10]
        cfgs = [CaptureConfig(str(path.resolve()), sha, SampleConfig(motion=path.name, seed=s, video=video))
                for s in range(seeds or 1)]
        out.append(("real captures", path.stem, cfgs))
    return out


def _fields(sample) -> dict:
    """A SampleConfig's fields for the cache key; fields added later are left out at their off value,
    so the sessions made before them keep their keys (and their cached solves)."""
    d = asdict(sample)
    if not d.get("track_breaks"):
        d.pop("track_breaks", None)
    return d


def session_key(cfg) -> str:
    from uuomocap.synth import GENERATOR_VERSION

    if isinstance(cfg, CaptureConfig):
        from uuomocap.capture_session import GENERATOR_VERSION as CAPTURE_VERSION

        blob = json.dumps({"v": CAPTURE_VERSION, "sha1": cfg.sha1, **_fields(cfg.sample)}, sort_keys=True, default=str)
        return f"capture-{Path(cfg.file).stem}-s{cfg.sample.seed}-{hashlib.sha1(blob.encode()).hexdigest()[:10]}"

    blob = json.dumps({"v": GENERATOR_VERSION, **_fields(cfg)}, sort_keys=True, default=str)
    h = hashlib.sha1(blob.encode()).hexdigest()[:10]
    part = f"-{cfg.part}" if cfg.part else ""
    return f"{cfg.motion}-n{cfg.n_markers}{part}-o{cfg.occlusion:g}-s{cfg.seed}-{h}"


def ensure_session(cache: Path, cfg) -> Path:
    """Generate the session unless the cache already holds it (session.yaml is written last)."""
    from uuomocap.capture_session import make_capture_session
    from uuomocap.synth import make_session

    d = cache / "sessions" / session_key(cfg)
    if (d / "session.yaml").is_file():
        return d
    tmp = d.with_name(d.name + ".tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    if isinstance(cfg, CaptureConfig):
        make_capture_session(cfg.file, tmp, cfg.sample)
    else:
        make_session(tmp, cfg)
    tmp.rename(d)
    return d


def _mean(values) -> float:
    v = [float(x) for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else float("nan")


def summarise(runs: list[dict]) -> dict:
    """summary[method][scenario] = {metric: mean, 'sessions': n, 'failed': k, 'seconds': mean}."""
    out: dict = {}
    for r in runs:
        out.setdefault(r["method"], {}).setdefault(r["scenario"], []).append(r)
    summary: dict = {}
    for method, scen in out.items():
        summary[method] = {}
        for name, rs in scen.items():
            ok = [r for r in rs if r.get("metrics")]
            keys = sorted({k for r in ok for k, v in r["metrics"].items() if isinstance(v, (int, float, bool))})
            agg = {k: _mean([r["metrics"].get(k) for r in ok]) for k in keys if k not in ("frames", "rate_hz", "markers")}
            if "part_found" in agg:
                agg["part_found"] = 100.0 * agg["part_found"]
            agg["sessions"] = len(rs)
            agg["failed"] = len(rs) - len(ok)
            agg["seconds"] = _mean([r.get("seconds") for r in ok])
            det = [r["info"]["estimator"]["detection_rate"] for r in ok
                   if isinstance((r.get("info") or {}).get("estimator"), dict) and "detection_rate" in r["info"]["estimator"]]
            if det:
                agg["detection_rate"] = _mean(det)
            summary[method][name] = agg
    return summary


def format_tables(summary: dict, layout: list[tuple[str, str]], methods: list[str], pa_mpjpe: bool = False) -> str:
    """Paper-style tables: one per table group, rows = methods, 4 columns per scenario."""
    lines = []
    name_w = max([16] + [len(m) + 1 for m in methods])
    tables: dict[str, list[str]] = {}
    for table, scen in layout:
        tables.setdefault(table, [])
        if scen not in tables[table]:
            tables[table].append(scen)
    for table, scens in tables.items():
        partial = table == "partial body"
        cols = PART_COLUMNS if partial else FULL_COLUMNS
        if pa_mpjpe and not partial:
            cols = cols[:2] + (PA_COLUMN,) + cols[2:]
        widths = [max(8, len(h) + 1) for _, h in cols]
        width = sum(widths) + 1
        head1 = f"{'':<{name_w}}" + "".join(f"|{s:^{width - 1}}" for s in scens) + "|"
        head2 = f"{'method':<{name_w}}" + "".join("|" + "".join(f"{h:>{w}}" for (_, h), w in zip(cols, widths)) for _ in scens) + "|"
        lines += [f"{table}  (mm, MPJVE mm/s{'; part joints, found% = markers on the right part' if partial else ''})",
                  head1, head2, "-" * len(head2)]
        for m in methods:
            row = f"{m:<{name_w}}"
            for s in scens:
                agg = summary.get(m, {}).get(s, {})
                cells = ""
                for (key, _), w in zip(cols, widths):
                    v = agg.get(key, float("nan"))
                    cells += f"{v:{w}.1f}" if isinstance(v, float) and not math.isnan(v) else f"{'-':>{w}}"
                if agg.get("failed"):
                    cells = cells[:-1] + "!"
                row += "|" + cells
            lines.append(row + "|")
        lines.append("")
    fails = [(m, s, a["failed"], a["sessions"]) for m, ss in summary.items() for s, a in ss.items() if a.get("failed")]
    for m, s, k, n in fails:
        lines.append(f"! {m} failed on {k}/{n} sessions of {s}")
    times = {m: _mean([a["seconds"] for a in ss.values()]) for m, ss in summary.items()}
    det = {m: _mean([a["detection_rate"] for a in ss.values() if "detection_rate" in a]) for m, ss in summary.items()}
    det = {m: v for m, v in det.items() if not math.isnan(v)}
    if det:
        lines.append("video estimator: person detected in " + ", ".join(f"{100 * v:.1f} % of frames ({m})"
                                                                       for m, v in det.items()))
    lines.append("mean seconds per session: " + ", ".join(f"{m} {t:.1f}" for m, t in times.items()))
    return "\n".join(lines)


def run_bench(args) -> dict:
    from tqdm import tqdm

    from uuomocap.commands.eval import evaluate_paths
    from uuomocap.methods import METHODS

    if args.methods:
        methods = [m for item in args.methods for m in item.split(",") if m]
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            raise UserError(f"unknown method(s) {', '.join(unknown)}; registered: {', '.join(sorted(METHODS)) or 'none'}")
    elif args.suite == "smoke":
        # the smoke suite is a sanity check (~3 min on the 2-core CPU): the reference, the baselines and our solvers;
        # ablations and slow variants run in `full` or with --methods
        methods = [m for m in SMOKE_METHODS if m in METHODS]
    else:
        methods = sorted(METHODS)
    if not methods:
        raise UserError("no methods are registered")
    motions = tuple(m for item in (args.motions or []) for m in item.split(",") if m) or None
    only = tuple(s.strip() for item in (getattr(args, "scenarios", None) or []) for s in item.split(",") if s.strip())
    captures = [f for item in (getattr(args, "captures", None) or []) for f in item.split(",") if f]
    if captures:
        scenarios = capture_scenarios(captures, args.seeds, args.video)
    else:
        scenarios = suite_scenarios(args.suite, args.seeds, motions, args.video, getattr(args, "duration", None), only or None)
    cache = Path(args.cache) if args.cache else default_cache()
    cache.mkdir(parents=True, exist_ok=True)

    # Unique sessions (occlusion 0 at 40 markers is the same session as "40 markers").
    jobs = [(table, scen, cfg) for table, scen, cfgs in scenarios for cfg in cfgs]
    unique = {session_key(cfg): cfg for _, _, cfg in jobs}
    total = len(unique) + len(unique) * len(methods)
    bar = tqdm(total=total, desc=f"bench {args.suite}", unit="job", file=sys.stderr, disable=args.quiet)
    session_dirs: dict[str, Path] = {}
    t0 = time.perf_counter()
    for key, cfg in unique.items():
        bar.set_postfix_str(f"generate {key[:28]}")
        try:
            session_dirs[key] = ensure_session(cache, cfg)
        except (ValueError, OSError) as exc:  # MarkerFileError is a ValueError
            bar.close()
            raise UserError(f"generating session {key}: {exc}") from None
        bar.update(1)
    gen_seconds = time.perf_counter() - t0

    results: dict[tuple[str, str], dict] = {}
    gt_m2s: dict[str, float] = {}
    # the methods run one after another: each gets every core (uuo-window keeps one, as live)
    threads = solo_thread_count(getattr(args, "threads", None))
    for key, sdir in session_dirs.items():
        for method in methods:
            bar.set_postfix_str(f"{method} {key[:24]}")
            out = cache / "outputs" / key / f"{method}.npz"
            out.parent.mkdir(parents=True, exist_ok=True)
            if out.exists():
                out.unlink()
            rec: dict = {"method": method, "session": key}
            ts = time.perf_counter()
            try:
                with torch_threads(threads):
                    info = METHODS[method](sdir, out, unique[key].body_model)
                rec["seconds"] = time.perf_counter() - ts
                rec["info"] = info if isinstance(info, dict) else {}
                metrics = evaluate_paths(out, sdir / "gt.npz", sdir / "markers.c3d", with_gt_m2s=key not in gt_m2s)
                if "m2s_gt" in metrics:
                    gt_m2s[key] = metrics["m2s_gt"]
                metrics["m2s_gt"] = gt_m2s.get(key, float("nan"))
                rec["metrics"] = metrics
                if method == "uuo-window":
                    for row, row_metrics in live_output_metrics(out, sdir / "gt.npz").items():
                        results[(row, key)] = {"method": row, "session": key, "seconds": rec["seconds"], "metrics": row_metrics}
            except KeyboardInterrupt:
                raise
            except UserError as exc:
                rec["error"] = f"evaluation: {exc}"
            except Exception as exc:  # a failing method must not stop the benchmark
                rec["error"] = f"{type(exc).__name__}: {exc}"
                rec["traceback"] = traceback.format_exc(limit=6)
            results[(method, key)] = rec
            bar.update(1)
    bar.close()

    rows = list(methods) + [row for _, row in LIVE_OUTPUT_ROWS if any(r == row for r, _ in results)]
    runs = []
    for table, scen, cfg in jobs:
        key = session_key(cfg)
        for method in rows:
            if (method, key) in results:
                runs.append({**results[(method, key)], "table": table, "scenario": scen})
    summary = summarise(runs)
    layout = [(t, s) for t, s, _ in scenarios]
    return {
        "suite": "captures" if captures else args.suite,
        "methods": methods,
        "cache": str(cache),
        "sessions": {k: {"dir": str(d), "config": asdict(unique[k]), "m2s_gt": gt_m2s.get(k)} for k, d in session_dirs.items()},
        "threads": threads,
        "generate_seconds": round(gen_seconds, 2),
        "total_seconds": round(time.perf_counter() - t0, 2),
        "scenarios": [{"table": t, "scenario": s, "sessions": len(c)} for t, s, c in scenarios],
        "summary": summary,
        "runs": runs,
        "table": format_tables(summary, layout, rows, pa_mpjpe=bool(getattr(args, "pa_mpjpe", False))),
    }


def _handler(args) -> int:
    res = run_bench(args)
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        from uuomocap.commands import _jsonable

        path.write_text(json.dumps(_jsonable(res), indent=1, allow_nan=True) + "\n", encoding="utf-8")
    print(res["table"])
    ref = [v["m2s_gt"] for v in res["sessions"].values() if v.get("m2s_gt") is not None]
    if ref:
        what = ("reference m2s (the labelled fit of the real markers)" if res["suite"] == "captures"
                else "ground truth m2s (markers 9.5 mm off the skin)")
        print(f"{what}: {np.mean(ref):.2f} mm; "
              f"{len(res['sessions'])} sessions (generation {res['generate_seconds']} s), total {res['total_seconds']} s "
              f"on {res['threads']} thread{'s' if res['threads'] != 1 else ''}"
              + (f"; JSON: {args.json}" if args.json else ""))
    failed = sum(1 for r in res["runs"] if "error" in r)
    return 1 if failed and args.strict else 0


def register_bench(subparsers) -> None:
    p = subparsers.add_parser(
        "accuracy",
        help="accuracy of every registered method on generated sessions (paper Tables 1/2)",
        description=(
            "Generate sessions deterministically from seeds (cached), run each method on the same inputs, "
            "evaluate (m2s, MPJPE, MPJVE, V2V; partial-body: the part's joints and whether the part was found) "
            "and print paper-style tables.  Suites: smoke (2 short sessions, ~3 min on 2 cores) and full (20/30/40/50 "
            "markers x seeds x motions; left leg / right arm / left shoulder; occlusion 0/0.2/1 %)."),
    )
    p.add_argument("--suite", choices=("smoke", "full"), default="smoke")
    p.add_argument("--methods", action="append", metavar="M[,M...]", help="methods to run (default: smoke - " + ",".join(SMOKE_METHODS) + "; full - all registered)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per scenario in the full suite (default 10)")
    p.add_argument("--motions", action="append", metavar="M[,M...]",
                   help=f"motions of the full suite (default {','.join(FULL_MOTIONS)})")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="session length in seconds (default: 8, smoke 2.5)")
    p.add_argument("--scenarios", action="append", metavar="NAME[,NAME...]",
                   help="run only these scenarios of the suite, e.g. '40 markers' or 'left_leg'")
    p.add_argument("--captures", action="append", metavar="FILE[,FILE...]",
                   help="instead of the suite: real LABELED captures (.c3d/.trc), each solved from its markers with the "
                        "labels taken away and scored against its labelled fit (`uuomocap sample from-capture`)")
    p.add_argument("--pa-mpjpe", action="store_true",
                   help="add a PA-MPJPE column (per-frame similarity-aligned) to the full-body tables")
    p.add_argument("--video", action="store_true", help="also render video.mp4 (for methods that run the video estimator)")
    p.add_argument("--cache", metavar="DIR", help=f"session cache (default {default_cache()})")
    p.add_argument("--json", metavar="FILE", help="write all results as JSON")
    p.add_argument("--strict", action="store_true", help="exit 1 when any method fails on any session")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_threads_flag(p)
    p.set_defaults(func=_handler)
