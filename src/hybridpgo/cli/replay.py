"""``hybridpgo replay FILE --budget-ms B``: the graph streamed frame by frame
(docs/mathematics.md, "Online streams")."""

from __future__ import annotations

import argparse
import math
import os
from typing import Any

from ..errors import HybridPGOError
from ._common import describe_graph, log, print_json, print_table, read_input


def _check_outputs(prefix: str | None) -> None:
    """--plot needs matplotlib (the files themselves are checked by ``check_outputs``)."""
    if prefix is None:
        return
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise HybridPGOError("--plot needs matplotlib, which is not installed: "
                             "pip install hybridpgo[plot]") from None


#: ``--rerun-every 0``: about this many maps over the run.
RERUN_MAPS = 300


def _recorder(args: argparse.Namespace, graph: Any) -> Any:
    """The ``--rerun`` recorder (checked before the run), or None."""
    if getattr(args, "rerun", None) is None:
        return None
    from ..recording import RerunRecorder, rerun_available

    if not rerun_available():
        raise HybridPGOError("--rerun needs rerun-sdk, which is not installed: "
                             "pip install hybridpgo[rerun]")
    return RerunRecorder(graph, args.rerun, name=os.path.basename(args.file))


def _frame_recorder(recorder: Any, stream: Any, every: int, extra: int) -> Any:
    """``on_frame`` of :func:`~hybridpgo.online.replay.replay_online` logging to ``recorder``."""
    nf = stream.num_frames
    total = nf + extra
    every = every or max(1, math.ceil(total / RERUN_MAPS))
    ids = stream.graph.node_ids

    def on_frame(k: int, solver: Any, latency_s: float) -> None:
        kk = min(k, nf)
        _, robot = solver.pose(int(ids[stream.order[kk - 1]]))
        prefix = None
        if k % every == 0 or k in (nf, total):
            rot, trans = solver.estimate()
            prefix = stream.prefix(kk, rot, trans)
        recorder.frame(k, robot, latency_s * 1e3, prefix,
                       note=f" (extra frame {k - nf})" if k > nf else "")

    return on_frame


def replay_file(args: argparse.Namespace) -> dict[str, Any]:
    """Read, stream through the online solver (and iSAM2), measure; the JSON-friendly summary."""
    from ..online import OnlineConfig
    from ..online.replay import checkpoint_frames, make_stream

    _check_outputs(args.plot)
    graph = read_input(args.file, args.format)
    stream = make_stream(graph)
    if args.compare == "isam2":
        try:
            import gtsam  # noqa: F401
        except ImportError:
            raise HybridPGOError("--compare isam2 needs GTSAM, which is not installed: "
                                 "pip install hybridpgo[gtsam]") from None
        if graph.is_2d and graph.num_gps:
            raise HybridPGOError(f"{args.file}: --compare isam2: GPS readings on a 2D graph")
    try:
        options: dict[str, Any] = dict(tree=args.tree, tau_old=args.tau_old,
                                       local_size=args.local_size, robust=args.robust[0],
                                       robust_scale=args.robust[1])
        if args.background_refine is not None:
            options["background_refine"] = args.background_refine
        config = OnlineConfig(**options)
    except ValueError as exc:
        raise HybridPGOError(f"invalid online option: {exc}") from exc
    frames = checkpoint_frames(stream.num_frames, args.every) if args.every else []
    say = (lambda msg: None) if args.quiet else log
    say(f"replay: {describe_graph(graph)}, {stream.num_frames} frames, budget {args.budget_ms} ms")
    recorder = _recorder(args, graph)
    try:
        out = _run(args, graph, stream, config, frames, recorder, say)
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    if recorder is not None:
        recorder.close()
        out["rerun"] = {"path": args.rerun, "frames": recorder.frames}
    return out


def _run(args: argparse.Namespace, graph: Any, stream: Any, config: Any, frames: list[int],
         recorder: Any, say: Any) -> dict[str, Any]:
    from ..online.replay import prefix_optima, replay_isam2, replay_online

    budget = args.budget_ms * 1e-3
    on_frame = (None if recorder is None else
                _frame_recorder(recorder, stream, args.rerun_every, args.extra_frames))
    runs = [replay_online(stream, config, budget, checkpoints=frames,
                          extra_frames=args.extra_frames, on_frame=on_frame,
                          rate_hz=args.rate)]
    say(f"  hybridpgo: {runs[0].latency_s.sum():.1f} s in updates")
    if args.compare == "isam2":
        runs.append(replay_isam2(stream, checkpoints=frames, extra_frames=args.extra_frames))
        say(f"  isam2: {runs[1].latency_s.sum():.1f} s in updates")
    optima: dict[int, float] = {}
    if frames:
        say(f"  batch optima of {len(frames)} prefixes (exact LM)...")
        # with --robust auto, each prefix as the whole-graph default solves it
        optima = prefix_optima(stream, frames,
                               robust="auto" if config.robust == "auto" else "none")
    out: dict[str, Any] = {
        "path": str(args.file), "graph": describe_graph(graph), "frames": stream.num_frames,
        "budget_ms": args.budget_ms, "rate_hz": args.rate, "checkpoint_every": args.every,
        "optima": {str(k): v for k, v in optima.items()},
        "solvers": {r.name: {**r.summary(optima), "info": r.info} for r in runs},
    }
    if args.plot:
        out["plots"] = _plots(runs, optima, args.plot, args.budget_ms, os.path.basename(args.file))
    return out


def _plots(runs: list[Any], optima: dict[int, float], prefix: str, budget_ms: float,
           title: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..online.replay import energy_ratio
    from ..plot import save_figure

    written = []
    fig, ax = plt.subplots(figsize=(8, 4))
    for r in runs:
        ax.plot(r.latency_s * 1e3, lw=0.6, label=r.name)
    ax.axhline(budget_ms, color="k", ls="--", lw=0.8, label="budget")
    ax.set_yscale("log")
    ax.set_xlabel("frame")
    ax.set_ylabel("latency (ms)")
    ax.set_title(f"{title}: latency per frame")
    ax.legend()
    path = prefix + "_latency.png"
    save_figure(fig, path)
    plt.close(fig)
    written.append(path)
    if optima:
        fig, ax = plt.subplots(figsize=(8, 4))
        for r in runs:
            f = sorted(k for k in r.checkpoints if k in optima)
            ax.plot(f, [energy_ratio(r.checkpoints[k], optima[k]) for k in f], marker="o",
                    ms=3, label=r.name)
        ax.axhline(1.05, color="k", ls="--", lw=0.8, label="optimum + 5%")
        ax.set_yscale("log")
        ax.set_xlabel("frame")
        ax.set_ylabel("E / batch optimum of the prefix")
        ax.set_title(f"{title}: accuracy over time")
        ax.legend()
        path = prefix + "_energy.png"
        save_figure(fig, path)
        plt.close(fig)
        written.append(path)
    return written


def run(args: argparse.Namespace) -> int:
    s = replay_file(args)
    if args.json:
        print_json(s)
        return 0
    arrival = "back to back" if s["rate_hz"] is None else f"at {s['rate_hz']:g} Hz"
    rows = [("file", f"{s['path']} ({s['graph']})"), ("frames", f"{s['frames']}, {arrival}"),
            ("budget", f"{s['budget_ms']} ms per frame (add_*, update and the pose)")]
    for name, r in s["solvers"].items():
        line = (f"latency mean {r['latency_ms_mean']:.3f} ms, p99 {r['latency_ms_p99']:.3f}, "
                f"max {r['latency_ms_max']:.3f}, steady max {r['latency_ms_steady_max']:.3f}; "
                f"final E {r['final_energy']:.6g}")
        if "energy_ratio_max" in r:
            line += (f"; E/optimum: worst checkpoint {r['energy_ratio_max']:.4f}, "
                     f"end {r['final_ratio']:.4f}")
            if r.get("extra_ratio"):
                hit = r["extra_frames_to_1pct"]
                line += (f", after {len(r['extra_ratio'])} extra frames "
                         f"{r['extra_ratio'][-1]:.4f} (within 1% after "
                         f"{hit if hit is not None else 'never'})")
        if r.get("info", {}).get("rejected"):
            line += f"; {r['info']['rejected']} constraint(s) rejected as outliers"
        rows.append((name, line))
        for w in r.get("info", {}).get("worst_frames", [])[:3]:
            rows.append(("  worst frame", f"{w['frame']}: {w['cpu_ms']:.2f} ms CPU "
                         f"({w['edges']} edge(s), {w['gps']} GPS; relaxed {w['new']} new, "
                         f"{w['old']} old; {w['backlog']} left for later{_machine(w)})"))
    for path in s.get("plots", []):
        rows.append(("plot", path))
    if s.get("rerun"):
        rows.append(("rerun", f"{s['rerun']['path']} ({s['rerun']['frames']} frames recorded; "
                              "open with: rerun FILE)"))
    print_table(rows)
    return 0


def _machine(w: dict[str, Any]) -> str:
    """What the machine took from a worst frame, when anything: its wait for a CPU, the time
    the host took from the virtual machine's CPUs meanwhile, the garbage collections in it and
    its page faults (from 100: fresh memory written for the first time)."""
    parts = []
    if (w.get("waited_ms") or 0.0) >= 0.005:
        parts.append(f"{w['wall_ms']:.2f} ms wall, of it {w['waited_ms']:.2f} ms waiting for a "
                     "CPU")
    if w.get("stolen_ms"):
        parts.append(f"the host took {w['stolen_ms']:.0f} ms of CPU (both CPUs, 10 ms ticks)")
    if (w.get("collected_ms") or 0.0) >= 0.005:
        parts.append(f"{w['collected_ms']:.2f} ms of garbage collection")
    if (w.get("faults") or 0) >= 100:
        parts.append(f"{w['faults']} page faults")
    return "; " + ", ".join(parts) if parts else ""
