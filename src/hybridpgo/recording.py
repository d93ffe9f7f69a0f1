"""Record an optimization for the Rerun viewer (optional: ``pip install hybridpgo[rerun]``).

:class:`RerunRecorder` is an ``iterate`` callback of the solvers
(:data:`hybridpgo.solvers.gauss_newton.IterateCallback`): after every sweep and every polish or
exact iteration it logs, on the timeline ``iteration`` (0 = the start, counted across phases):

* ``graph/poses``: the positions (Points3D);
* ``graph/trajectory``: segments between poses adjacent in id order (LineStrips3D);
* ``graph/residuals``: each relative constraint from its desired position ``X_a Z_c`` to the
  actual position of b (paper Fig. 6), coloured dark brown (low χ²) to red (high) on this
  iteration's own log scale; ``graph/gps_residuals`` (blue): measured position to the pose;
* ``energy/total``, ``energy/per_constraint``, ``residuals/chi2_max``,
  ``residuals/chi2_median`` (Scalars) and a TextLog line ``log`` naming the phase.

An online run (``hybridpgo replay --rerun``) is logged by :meth:`RerunRecorder.frame` on the
timeline ``frame`` instead: every frame the newest pose (``robot``) and the update's time
(``latency_ms``), and at chosen frames the map received so far, as above.

Open the file with ``rerun FILE.rrd`` and scrub the ``iteration`` (or ``frame``) timeline.
The recording is written to a temporary file beside the target and renamed into place by
:meth:`close`, so a failed run leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import os
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ._output import Outputs
from .energy import constraint_energies
from .errors import FormatError, HybridPGOError
from .graph import FloatArray, PoseGraph

if TYPE_CHECKING:
    from .solvers.config import Progress

__all__ = ["RerunRecorder", "rerun_available"]

#: Residual colours, as :mod:`hybridpgo.plot`: dark brown (lowest χ²) to bright red (highest).
_LOW = np.array([0x3B, 0x1D, 0x0E], np.float64)
_HIGH = np.array([0xFF, 0x1A, 0x1A], np.float64)
_GPS = np.array([0x1F, 0x5F, 0xD0], np.uint8)
_TRAJECTORY = np.array([0x80, 0x80, 0x80], np.uint8)
_ROBOT = np.array([0x10, 0xA0, 0x30], np.uint8)


def rerun_available() -> bool:
    """True when the ``rerun-sdk`` package can be imported."""
    try:
        import rerun  # noqa: F401
    except ImportError:
        return False
    return True


def _trajectory_edges(graph: PoseGraph) -> npt.NDArray[np.int32]:
    """The edges drawn as the trajectory: between poses adjacent in id order (as
    :mod:`hybridpgo.plot`), or every edge when there is none."""
    a = graph.edge_nodes[:, 0]
    b = graph.edge_nodes[:, 1]
    consecutive = np.abs(a - b) == 1  # dense index = rank of the id
    if not consecutive.any():
        consecutive = np.ones_like(consecutive)
    return np.asarray(graph.edge_nodes[consecutive], np.int32)


def residual_colors(chi2: FloatArray) -> npt.NDArray[np.uint8]:
    """(k, 3) uint8 colours of χ² values on their own log scale (brown low, red high)."""
    k = chi2.shape[0]
    finite = np.isfinite(chi2)
    level = np.ones(k)  # a non-finite chi2 is drawn at the top of the scale
    if finite.any():
        logs = np.log10(np.maximum(chi2[finite], 1e-300))
        hi = float(logs.max())
        lo = max(float(logs.min()), hi - 6.0)  # six decades at most, as a readable scale
        level[finite] = np.clip((logs - lo) / (hi - lo), 0.0, 1.0) if hi > lo else 1.0
    rgb = _LOW[None, :] + level[:, None] * (_HIGH - _LOW)[None, :]
    return np.asarray(np.rint(rgb), np.uint8)


class RerunRecorder:
    """Log poses and residuals of every iteration to a ``.rrd`` file (see the module doc).

    Parameters
    ----------
    graph : PoseGraph
    path : str or os.PathLike
        The ``.rrd`` file to write (atomically, at :meth:`close`).
    name : str, optional
        The recording's name in the viewer (default: the file's base name).

    Raises
    ------
    HybridPGOError
        rerun-sdk is not installed.
    """

    def __init__(self, graph: PoseGraph, path: str | os.PathLike[str], *,
                 name: str | None = None) -> None:
        try:
            import rerun as rr
        except ImportError:
            raise HybridPGOError("recording needs the rerun-sdk package, which is not "
                                 "installed: pip install hybridpgo[rerun]") from None
        self._rr = rr
        self.graph = graph
        self.path = os.fspath(path)
        self.frames = 0
        """Iterations logged so far."""
        try:
            self._out: Outputs | None = Outputs([self.path])
        except FormatError as exc:
            raise HybridPGOError(f"{self.path}: cannot write the recording: "
                                 f"{exc.problem}") from exc
        self._rec = rr.RecordingStream("hybridpgo")
        self._rec.save(self._out.temp(self.path))
        self._rec.send_recording_name(name or os.path.basename(self.path))
        self._traj = _trajectory_edges(graph)

    def __call__(self, progress: Progress, rotations: FloatArray,
                 translations: FloatArray) -> None:
        """Log one iteration (the solvers' ``iterate`` callback)."""
        self._rec.set_time("iteration", sequence=self.frames)
        self._log_map(self.graph, rotations, translations, self._traj)
        tau = "" if progress.tau is None else f", tau {progress.tau:.4g}"
        what = f"{progress.phase} ({progress.detail})" if progress.detail else progress.phase
        self._rec.log("log", self._rr.TextLog(
            f"{what} {progress.iteration}/{progress.total}: E {progress.energy:.6g}{tau}"))
        self.frames += 1

    def frame(self, frame: int, robot: FloatArray, latency_ms: float,
              prefix: PoseGraph | None = None, note: str = "") -> None:
        """Log one frame of an online run (``hybridpgo replay``) on the timeline ``frame``.

        ``robot`` is the newest pose's position and ``latency_ms`` the frame's update time;
        ``prefix``, when given, is the map so far at the current estimate (the graph of the
        poses and constraints received up to this frame), logged like an iteration of
        :meth:`__call__` — poses, trajectory, residuals and energy over the prefix.
        """
        rr = self._rr
        rec = self._rec
        rec.set_time("frame", sequence=frame)
        rec.log("robot", rr.Points3D(np.asarray(robot, np.float64).reshape(1, 3),
                                     colors=_ROBOT, radii=rr.Radius.ui_points(6.0)))
        rec.log("latency_ms", rr.Scalars(float(latency_ms)))
        if prefix is not None:
            e = self._log_map(prefix, prefix.rotations, prefix.translations,
                              _trajectory_edges(prefix))
            rec.log("log", rr.TextLog(f"frame {frame}: {prefix.num_nodes} poses, "
                                      f"E {e:.6g}{note}"))
        self.frames += 1

    def _log_map(self, g: PoseGraph, rotations: FloatArray, translations: FloatArray,
                 traj: npt.NDArray[np.int32]) -> float:
        """Log the poses, trajectory, residuals and energies of ``g`` at the given poses; E."""
        rr = self._rr
        rec = self._rec
        t = np.asarray(translations, np.float64)
        s_rel, s_gps = constraint_energies(g, rotations, translations)
        a = g.edge_nodes[:, 0]
        desired = np.einsum("nij,nj->ni", rotations[a], g.edge_translations) + t[a]
        rec.log("graph/poses", rr.Points3D(t, radii=rr.Radius.ui_points(2.0)))
        rec.log("graph/trajectory", rr.LineStrips3D(
            np.stack([t[traj[:, 0]], t[traj[:, 1]]], axis=1), colors=_TRAJECTORY,
            radii=rr.Radius.ui_points(1.0)))
        rec.log("graph/residuals", rr.LineStrips3D(
            np.stack([desired, t[g.edge_nodes[:, 1]]], axis=1), colors=residual_colors(s_rel),
            radii=rr.Radius.ui_points(1.0)))
        if g.num_gps:
            rec.log("graph/gps_residuals", rr.LineStrips3D(
                np.stack([g.gps_positions, t[g.gps_nodes]], axis=1), colors=_GPS,
                radii=rr.Radius.ui_points(1.0)))
        e = float(s_rel.sum() + s_gps.sum())
        all_s = np.concatenate([s_rel, s_gps])
        rec.log("energy/total", rr.Scalars(e))
        rec.log("energy/per_constraint", rr.Scalars(e / max(all_s.shape[0], 1)))
        if all_s.shape[0]:
            rec.log("residuals/chi2_max", rr.Scalars(float(all_s.max())))
            rec.log("residuals/chi2_median", rr.Scalars(float(np.median(all_s))))
        return e

    def close(self) -> None:
        """Finish the file and move it into place (a FIFO or device is written into)."""
        self._rec.flush()
        self._rec.disconnect()
        if self._out is None:
            return
        try:
            self._out.commit()
        except FormatError as exc:
            raise HybridPGOError(f"{self.path}: cannot write the recording: "
                                 f"{exc.problem}") from exc
        finally:
            self._out = None

    def abort(self) -> None:
        """Stop recording and remove the temporary file (nothing is written)."""
        with contextlib.suppress(Exception):
            self._rec.disconnect()
        if self._out is not None:
            self._out.discard()
            self._out = None
