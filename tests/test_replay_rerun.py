"""``hybridpgo replay --rerun``: the online run recorded frame by frame (hybridpgo.recording)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import energy
from hybridpgo.io import read_graph
from hybridpgo.online import OnlineConfig
from hybridpgo.online.replay import make_stream, replay_online


class _Calls:
    """A stand-in recorder: what :meth:`RerunRecorder.frame` was given."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, np.ndarray, float, object, str]] = []
        self.energies: dict[int, float] = {}

    def frame(self, k: int, robot: np.ndarray, latency_ms: float, prefix: object = None,
              note: str = "") -> None:
        self.calls.append((k, np.array(robot), latency_ms, prefix, note))


def test_frame_recorder_logs_the_prefix_at_the_current_estimate(tiny: Path) -> None:
    from hybridpgo.cli.replay import _frame_recorder

    graph = read_graph(tiny)
    stream = make_stream(graph)
    rec = _Calls()
    on_frame = _frame_recorder(rec, stream, 4, 3)
    solver_energy: dict[int, float] = {}
    robots: dict[int, np.ndarray] = {}

    def both(k: int, solver: object, latency_s: float) -> None:
        on_frame(k, solver, latency_s)
        solver_energy[k] = solver.energy()  # type: ignore[attr-defined]
        kk = min(k, stream.num_frames)
        robots[k] = solver.pose(int(graph.node_ids[stream.order[kk - 1]]))[1]  # type: ignore

    res = replay_online(stream, OnlineConfig(background_refine=False), 5e-3, extra_frames=3,
                        on_frame=both)
    nf = stream.num_frames
    assert [c[0] for c in rec.calls] == list(range(1, nf + 4))
    maps = {c[0]: c[3] for c in rec.calls if c[3] is not None}
    assert sorted(maps) == [4, 8, 9, 12]  # every 4th, the last frame, the last extra frame
    for k, prefix in maps.items():
        kk = min(k, nf)
        assert prefix.num_nodes == kk  # type: ignore[attr-defined]
        np.testing.assert_array_equal(prefix.node_ids,  # type: ignore[attr-defined]
                                      np.sort(graph.node_ids[stream.order[:kk]]))
        e = energy(prefix, prefix.rotations, prefix.translations)  # type: ignore[arg-type]
        assert e == pytest.approx(solver_energy[k], rel=FLOAT64_IDENTITY)
    for k, robot, lat, _, note in rec.calls:
        np.testing.assert_array_equal(robot, robots[k])
        assert lat > 0 and (note.startswith(" (extra frame") == (k > nf))
    np.testing.assert_array_equal([c[2] * 1e-3 for c in rec.calls[:nf]], res.latency_s)


def _recorded(path: Path, timeline: str) -> dict[str, int]:
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static or timeline not in chunk.timeline_names:
            continue
        counts[chunk.entity_path] = counts.get(chunk.entity_path, 0) + chunk.num_rows
    return counts


@pytest.mark.parametrize(("every", "maps"), [(0, 12), (5, 4)])
def test_replay_rerun_records_every_frame(capsys: pytest.CaptureFixture[str], tiny: Path,
                                          tmp_path: Path, every: int, maps: int) -> None:
    pytest.importorskip("rerun")
    rrd = tmp_path / "run.rrd"
    code, out, err = run_cli(capsys, "replay", tiny, "--every", "0", "--extra-frames", "3",
                             "--no-background-refine",
                             "--rerun", rrd, "--rerun-every", every, "--json", "--quiet")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["rerun"] == {"path": str(rrd), "frames": 12}  # 9 frames + 3 extra
    counts = _recorded(rrd, "frame")
    assert counts["/robot"] == counts["/latency_ms"] == 12
    for entity in ("/graph/poses", "/graph/trajectory", "/graph/residuals", "/energy/total",
                   "/log"):
        assert counts.get(entity) == maps, (entity, counts)
    assert [p.name for p in tmp_path.iterdir()] == ["run.rrd"]


def test_replay_rerun_refusals(capsys: pytest.CaptureFixture[str], tiny: Path, tmp_path: Path,
                               monkeypatch: pytest.MonkeyPatch) -> None:
    copy = tmp_path / "g.g2o"
    copy.write_bytes(tiny.read_bytes())
    code, _, err = run_cli(capsys, "replay", copy, "--rerun", copy)
    assert code == 2 and "--rerun" in err and copy.read_bytes() == tiny.read_bytes()
    monkeypatch.setattr("hybridpgo.recording.rerun_available", lambda: False)
    rrd = tmp_path / "run.rrd"
    code, _, err = run_cli(capsys, "replay", copy, "--rerun", rrd, "--every", "0")
    assert code == 2
    assert err.strip().splitlines()[-1] == ("hybridpgo: error: --rerun needs rerun-sdk, which "
                                            "is not installed: pip install hybridpgo[rerun]")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.g2o"]


def test_replay_plot_outputs_are_checked_before_the_run(capsys: pytest.CaptureFixture[str],
                                                        tiny: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    target = tmp_path / "p_latency.png"
    target.mkdir()
    code, _, err = run_cli(capsys, "replay", tiny, "--plot", tmp_path / "p", "--every", "0")
    assert code == 2 and "it is a directory" in err
