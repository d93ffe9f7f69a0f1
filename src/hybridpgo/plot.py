"""Plots of pose graphs and of solver progress (matplotlib: ``pip install hybridpgo[plot]``).

* :func:`plot_graph` draws a graph top-down: the trajectory (edges between poses adjacent in id
  order) as
  a thin line and each constraint's *residual* as a line from its desired position of b
  (``X_a · Z_c``) to b's actual position, from brown to bright red by the constraint's energy
  (paper Fig. 6); GPS residuals are blue lines from the measured position to the pose (paper
  Fig. 3d).  :func:`plot_graph_3d` is the same in an oblique 3D view.
* :func:`plot_energy` draws energy per constraint against wall time for several solver results
  (paper Fig. 5).
* :func:`graph_figure` and :func:`energy_figure` build whole figures; :func:`save_figure`
  writes one atomically.

Every map has a legend (trajectory, residuals, GPS residuals, start and end markers), its
energy per constraint in the title, and, for oblique views, a horizontal scale bar.  Each map's
colour scale is its own by default (so an optimized map shows *its* worst residuals in red);
pass ``energy_range`` (:func:`residual_energy_range`) to compare maps on one scale.

Every ``plot_*`` function takes ``ax=None`` (a new figure is made) and returns the axes.  Figures
are made with :class:`matplotlib.figure.Figure` on the Agg canvas, never through ``pyplot``, so
nothing here opens a window or changes matplotlib's global backend.  Segments are drawn as
NaN-separated lines, a few per colour level, so a 40 000-pose graph draws in a few seconds.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ._output import Outputs
from .errors import FormatError, HybridPGOError
from .graph import FloatArray, PoseGraph

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.colors import Colormap, Normalize
    from matplotlib.figure import Figure

    from .solvers.result import SolveResult

__all__ = [
    "energy_figure",
    "energy_title",
    "graph_figure",
    "height_scale",
    "legend_handles",
    "oblique_projection",
    "plot_energy",
    "plot_graph",
    "plot_graph_3d",
    "residual_energy_range",
    "save_figure",
]

#: Residual colours: dark brown (lowest energy) to bright red (highest), as in paper Fig. 6.
RESIDUAL_COLORS = ("#3b1d0e", "#8b4513", "#ff1a1a")
#: GPS residuals are blue (paper Fig. 3d).
GPS_COLOR = "#1f5fff"
TRAJECTORY_COLOR = "0.55"
#: Start (first pose in id order) and end (last) markers.
START_STYLE = {"marker": "o", "color": "#1a9e3a", "markersize": 8, "markeredgecolor": "white"}
END_STYLE = {"marker": "s", "color": "#111111", "markersize": 7, "markeredgecolor": "white"}
#: The colour scale spans at most this many decades below the highest energy.
ENERGY_DECADES = 4.0


def _require_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise HybridPGOError("plotting needs matplotlib, which is not installed: "
                             "pip install hybridpgo[plot]") from exc


def _new_figure(figsize: tuple[float, float] = (7.0, 7.0)) -> Figure:
    """A figure on the Agg canvas (no pyplot, no window)."""
    _require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _residual_cmap() -> Colormap:
    from matplotlib.colors import LinearSegmentedColormap

    return LinearSegmentedColormap.from_list("hybridpgo_residual", list(RESIDUAL_COLORS))


def _energy_norm(energy_range: tuple[float, float] | None, energies: FloatArray) -> Normalize:
    from matplotlib.colors import LogNorm, Normalize

    if energy_range is None:
        energy_range = _energy_range([energies])
    lo, hi = energy_range
    if not (hi > 0):
        return Normalize(0.0, 1.0, clip=True)
    return LogNorm(lo, hi, clip=True)


def _energy_range(all_energies: Sequence[FloatArray]) -> tuple[float, float]:
    """Colour range shared by several panels: the highest energy and ENERGY_DECADES below it."""
    hi = max((float(e.max()) for e in all_energies if e.size), default=0.0)
    if not (hi > 0 and np.isfinite(hi)):
        return (0.0, 0.0)
    pos = [e[e > 0] for e in all_energies]
    lo_data = min((float(p.min()) for p in pos if p.size), default=hi)
    return (max(lo_data, hi * 10.0 ** -ENERGY_DECADES), hi) if lo_data < hi else (hi / 10, hi)


def _poses(graph: PoseGraph, rot: FloatArray | None,
           trans: FloatArray | None) -> tuple[FloatArray, FloatArray]:
    """The poses to draw: the given ones, the file's, or the tree initialization (iSAM)."""
    from ._poses import given_or_start

    return given_or_start(graph, rot, trans, ("rot", "trans"))


def _segments(graph: PoseGraph, rot: FloatArray, trans: FloatArray) -> dict[str, Any]:
    """Line segments (k, 2, 3) of the trajectory and of the residuals, with energies."""
    from .energy import constraint_energies

    a = graph.edge_nodes[:, 0]
    b = graph.edge_nodes[:, 1]
    consecutive = np.abs(a - b) == 1  # neighbours in id order (dense index = rank of the id)
    if not consecutive.any():  # ids carry no order: draw every edge as the "trajectory"
        consecutive = np.ones_like(consecutive)
    traj = np.stack([trans[a[consecutive]], trans[b[consecutive]]], axis=1)
    # desired position of b: X_a · Z_c applied to the origin = R_a t_ab + t_a
    desired = np.einsum("nij,nj->ni", rot[a], graph.edge_translations) + trans[a]
    residual = np.stack([desired, trans[b]], axis=1)
    gps = np.stack([graph.gps_positions, trans[graph.gps_nodes]], axis=1)
    e_rel, e_gps = constraint_energies(graph, rot, trans)
    return {"trajectory": traj, "residual": residual, "residual_energy": e_rel, "gps": gps,
            "gps_energy": e_gps}


def _graph_energies(graph: PoseGraph, rot: FloatArray | None,
                    trans: FloatArray | None) -> FloatArray:
    from .energy import constraint_energies

    r, t = _poses(graph, rot, trans)
    return constraint_energies(graph, r, t)[0]


def _draw_segments(ax: Axes, seg: FloatArray, *, color: Any, linewidth: float, zorder: float,
                   label: str | None = None) -> None:
    """Draw (k, 2, 2) segments as ONE Line2D with NaN separators.

    A ``LineCollection`` makes one ``Path`` per segment (~25 us each: 2.5 s per 100 000
    segments, measured on matplotlib 3.11); one NaN-separated line draws the same in ~0.1 s.
    """
    if seg.shape[0] == 0:
        return
    gapped = np.full((seg.shape[0], 3, 2), np.nan)
    gapped[:, :2] = seg
    pts = gapped.reshape(-1, 2)
    ax.plot(pts[:, 0], pts[:, 1], color=color, linewidth=linewidth, zorder=zorder, label=label,
            solid_capstyle="butt")


#: Residuals are drawn in this many colour levels (one line object per level, see
#: :func:`_draw_segments`); 64 levels are indistinguishable from a continuous scale.
COLOR_LEVELS = 64


def _draw_residuals(ax: Axes, seg: FloatArray, energies: FloatArray, norm: Normalize,
                    cmap: Colormap, zorder: float) -> None:
    """Residual segments coloured by energy, the highest energies drawn last (on top)."""
    if seg.shape[0] == 0:
        return
    level = np.clip(np.asarray(norm(energies).filled(0.0)), 0.0, 1.0)
    bins = np.minimum((level * COLOR_LEVELS).astype(np.int64), COLOR_LEVELS - 1)
    for k in np.unique(bins):
        _draw_segments(ax, seg[bins == k], color=cmap((k + 0.5) / COLOR_LEVELS),
                       linewidth=0.9, zorder=zorder + k / COLOR_LEVELS)


def energy_title(graph: PoseGraph, rot: FloatArray | None = None,
                 trans: FloatArray | None = None) -> str:
    """``E/c 1.167  (E 6533, 5453 constraints)``: the energy line of a map's title."""
    from .energy import energy

    r, t = _poses(graph, rot, trans)
    e = energy(graph, r, t)
    nc = graph.num_constraints
    return f"E/c {e / max(nc, 1):.4g}  (E {e:.4g}, {nc} constraints)"


def _colorbar(fig: Any, norm: Normalize, axes: Axes | Sequence[Axes]) -> None:
    from matplotlib.cm import ScalarMappable

    fig.colorbar(ScalarMappable(norm=norm, cmap=_residual_cmap()), ax=axes, shrink=0.8,
                 label=r"constraint energy $e^\top \Omega\, e$")


def legend_handles(graph: PoseGraph, residuals: bool = True) -> list[Any]:
    """Legend entries of a map: trajectory, residuals, GPS residuals (if any), start, end."""
    from matplotlib.lines import Line2D

    handles: list[Any] = [Line2D([], [], color=TRAJECTORY_COLOR, linewidth=1.0,
                                 label="trajectory (consecutive poses)")]
    if residuals:
        handles.append(Line2D([], [], color=RESIDUAL_COLORS[-1], linewidth=1.5,
                              label="residual: desired \u2192 actual pose (redder: higher energy)"))
        if graph.num_gps:
            handles.append(Line2D([], [], color=GPS_COLOR, linewidth=1.5,
                                  label="GPS residual: measured \u2192 actual"))
    first, last = int(graph.node_ids[0]), int(graph.node_ids[-1])
    handles.append(Line2D([], [], linestyle="none", label=f"start (pose {first})",
                          **START_STYLE))  # type: ignore[arg-type]
    handles.append(Line2D([], [], linestyle="none", label=f"end (pose {last})",
                          **END_STYLE))  # type: ignore[arg-type]
    return handles


def _legend_below(ax: Axes, handles: list[Any]) -> None:
    """A legend under the axes (never over the map; loc="best" is slow on 100k points)."""
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.07),
              ncols=2, fontsize="small", frameon=False)


def _finish_panel(ax: Axes, norm: Normalize | None, colorbar: bool, title: str | None,
                  xlabel: str, ylabel: str) -> None:
    if norm is not None and colorbar and ax.figure is not None:
        _colorbar(ax.figure, norm, ax)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)


def _title(title: str | None, graph: PoseGraph, rot: FloatArray, trans: FloatArray,
           with_energy: bool) -> str | None:
    if not with_energy:
        return title
    line = energy_title(graph, rot, trans)
    return f"{title}\n{line}" if title else line


def _nice_length(span: float) -> float:
    """1, 2 or 5 x 10^k metres, about a fifth of ``span``."""
    target = max(span / 5.0, 1e-9)
    k = np.floor(np.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**k <= target:
            return float(m * 10.0**k)
    return float(10.0**k)  # pragma: no cover - m = 1 always fits


def _fmt_length(metres: float) -> str:
    if metres >= 1000.0:
        return f"{metres / 1000.0:g} km"
    if metres >= 1.0:
        return f"{metres:g} m"
    return f"{metres * 100.0:g} cm"


def _scale_bar(ax: Axes, span: float) -> float:
    """A horizontal scale bar in the lower left; returns its length (metres)."""
    from mpl_toolkits.axes_grid1.anchored_artists import (
        AnchoredSizeBar,
    )

    length = _nice_length(span)
    bar = AnchoredSizeBar(ax.transData, length, _fmt_length(length), loc="lower left",
                          pad=0.5, borderpad=0.6, sep=4, frameon=False, size_vertical=0,
                          color="black")
    bar.set_gid("scale-bar")
    ax.add_artist(bar)
    return length


def _draw_graph(ax: Axes, graph: PoseGraph, project: Callable[[FloatArray], FloatArray],
                rot: FloatArray, trans: FloatArray, residuals: bool,
                energy_range: tuple[float, float] | None) -> Normalize | None:
    """Draw trajectory, poses and residuals after ``project`` ((k, 3) -> (k, 2))."""
    seg = _segments(graph, rot, trans)

    def proj(s: FloatArray) -> FloatArray:
        return project(s.reshape(-1, 3)).reshape(s.shape[0], 2, 2)

    _draw_segments(ax, proj(seg["trajectory"]), color=TRAJECTORY_COLOR, linewidth=0.5,
                   zorder=1)
    p = project(trans)
    ax.plot(p[:, 0], p[:, 1], linestyle="none", marker=".", markersize=1.0, color="0.35",
            zorder=2)
    # start and end of the trajectory (first and last pose in id order), above everything
    ax.plot(p[:1, 0], p[:1, 1], linestyle="none", zorder=7, **START_STYLE)  # type: ignore[arg-type]
    ax.plot(p[-1:, 0], p[-1:, 1], linestyle="none", zorder=7, **END_STYLE)  # type: ignore[arg-type]
    if not residuals:
        return None
    e = seg["residual_energy"]
    norm = _energy_norm(energy_range, e)
    _draw_residuals(ax, proj(seg["residual"]), e, norm, _residual_cmap(), zorder=3)
    _draw_segments(ax, proj(seg["gps"]), color=GPS_COLOR, linewidth=0.9, zorder=5)
    return norm


def plot_graph(graph: PoseGraph, rot: FloatArray | None = None, trans: FloatArray | None = None,
               ax: Axes | None = None, residuals: bool = True, *,
               energy_range: tuple[float, float] | None = None, colorbar: bool = True,
               title: str | None = None, legend: bool = True,
               energy_in_title: bool = True) -> Axes:
    """Draw ``graph`` top-down (x right, y up) with its constraint residuals (paper Fig. 6).

    Parameters
    ----------
    graph : PoseGraph
    rot, trans : (N, 3, 3), (N, 3) float64, optional
        Poses to draw (R_world_node, t_world_node); default: the graph's vertices, or the tree
        initialization when the file had none (iSAM).
    ax : matplotlib Axes, optional
        Axes to draw into; default: a new figure.
    residuals : bool
        Draw each relative constraint's residual (desired position of b, ``X_a · Z_c``, to b's
        actual position), coloured from brown to bright red by its energy on a log scale, and
        each GPS residual (measured position to the pose) in blue.
    energy_range : (low, high), optional
        Energies at the ends of the colour scale (to compare maps on one scale, see
        :func:`residual_energy_range`); default: this map's own energies, so its highest-energy
        residuals are the reddest.
    colorbar : bool
        Add a colour bar of the constraint energy (with ``residuals``).
    title : str, optional
    legend : bool
        A legend under the map: trajectory, residuals, GPS residuals, start and end markers.
    energy_in_title : bool
        Add a title line with the energy per constraint (:func:`energy_title`).

    Returns
    -------
    Axes
    """
    _require_matplotlib()
    rot, trans = _poses(graph, rot, trans)
    if ax is None:
        ax = _new_figure().add_subplot()
    norm = _draw_graph(ax, graph, lambda p: p[:, :2], rot, trans, residuals, energy_range)
    _finish_panel(ax, norm, colorbar, _title(title, graph, rot, trans, energy_in_title),
                  "x [m]", "y [m]")
    if legend:
        _legend_below(ax, legend_handles(graph, residuals))
    return ax


def oblique_projection(points: FloatArray, *, azim: float = -60.0, elev: float = 30.0,
                       z_scale: float = 1.0) -> FloatArray:
    """Project (k, 3) world points to (k, 2) for an oblique view.

    As in matplotlib's 3D axes, the camera sits at azimuth ``azim`` (degrees from +x towards +y)
    and elevation ``elev`` (90: top-down, 0: from the side), looking at the scene; heights are
    multiplied by ``z_scale``.  Screen x points to the camera's right, screen y up.
    """
    a, e = np.radians(azim), np.radians(elev)
    fwd = np.array([-np.cos(a), -np.sin(a), 0.0])  # horizontal viewing direction
    right = np.array([-np.sin(a), np.cos(a), 0.0])  # fwd x up
    p = np.asarray(points, np.float64)
    return np.column_stack([p @ right,
                            (p @ fwd) * np.sin(e) + p[:, 2] * z_scale * np.cos(e)])


def _auto_z_scale(trans: FloatArray) -> float:
    """Stretch heights so that their extent is at least 15 % of the horizontal extent."""
    ext = trans.max(axis=0) - trans.min(axis=0)
    horiz = max(float(ext[0]), float(ext[1]))
    if ext[2] <= 0 or horiz <= 0:
        return 1.0
    return max(1.0, 0.15 * horiz / float(ext[2]))


def plot_graph_3d(graph: PoseGraph, rot: FloatArray | None = None,
                  trans: FloatArray | None = None, ax: Axes | None = None,
                  residuals: bool = True, *, energy_range: tuple[float, float] | None = None,
                  elev: float = 30.0, azim: float = -60.0, z_scale: float | None = None,
                  colorbar: bool = False, title: str | None = None, legend: bool = True,
                  energy_in_title: bool = True, scale_bar: bool = True) -> Axes:
    """Draw ``graph`` in an oblique view (paper Fig. 6c/d), same colours as :func:`plot_graph`.

    The view is an orthographic projection (:func:`oblique_projection`) drawn on ordinary 2D
    axes (mplot3d re-projects every segment in Python at each draw: 10 s for 50 000 poses).
    ``z_scale`` exaggerates heights (default: so that they span at least 15 % of the horizontal
    extent, which makes vertical residuals visible; the factor is given in the title).  The
    view has no axis ticks; ``scale_bar`` draws a horizontal one in metres instead (screen x is
    a true horizontal distance in an orthographic view; screen y mixes depth and height).
    """
    _require_matplotlib()
    rot, trans = _poses(graph, rot, trans)
    if ax is None:
        ax = _new_figure().add_subplot()
    zs = _auto_z_scale(trans) if z_scale is None else float(z_scale)

    def project(p: FloatArray) -> FloatArray:
        return oblique_projection(p, azim=azim, elev=elev, z_scale=zs)

    norm = _draw_graph(ax, graph, project, rot, trans, residuals, energy_range)
    label = f"oblique view (azimuth {azim:g}, elevation {elev:g} deg, heights x{zs:.3g})"
    head = _title(title, graph, rot, trans, energy_in_title)
    _finish_panel(ax, norm, colorbar, f"{head}\n{label}" if head else label, "", "")
    ax.set_xticks([])
    ax.set_yticks([])
    if scale_bar:
        screen_x = project(trans)[:, 0]
        _scale_bar(ax, float(np.ptp(screen_x)) if screen_x.size else 0.0)
    if legend:
        _legend_below(ax, legend_handles(graph, residuals))
    return ax


def plot_energy(results: Mapping[str, SolveResult], ax: Axes | None = None, *,
                title: str | None = None) -> Axes:
    """Energy per constraint against wall time, log y (paper Fig. 5).

    Parameters
    ----------
    results : {name: SolveResult}
        One line per result: ``energy_history / num_constraints`` against ``times``.  The exact
        polish of a ``hybrid+polish`` result is drawn dashed.
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    _require_matplotlib()
    if ax is None:
        ax = _new_figure((7.0, 4.5)).add_subplot()
    for k, (name, res) in enumerate(results.items()):
        color = f"C{k % 10}"
        e = np.asarray(res.energy_history, np.float64) / max(res.num_constraints, 1)
        t = np.asarray(res.times, np.float64)
        split = res.iterations + 1 if "polish_iterations" in res.stats else e.shape[0]
        ax.plot(t[:split], e[:split], marker="o", markersize=3, color=color, label=name)
        if split < e.shape[0]:
            ax.plot(t[split - 1:], e[split - 1:], marker="s", markersize=3, linestyle="--",
                    color=color, label=f"{name}: exact polish")
    ax.set_yscale("log")
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("energy per constraint")
    ax.grid(True, which="both", alpha=0.3)
    if results:
        ax.legend()
    if title:
        ax.set_title(title)
    return ax


def graph_figure(graph: PoseGraph,
                 poses: Sequence[tuple[FloatArray, FloatArray] | None] | None = None, *,
                 titles: Sequence[str] | None = None, residuals: bool = True,
                 energy_range: tuple[float, float] | None = None,
                 z_scale: float | None = None, energy_in_title: bool = True) -> Figure:
    """A figure with one column per pose set: top-down, plus an oblique 3D view for 3D graphs.

    ``poses`` is a list of ``(rot, trans)`` (``None`` entries: the graph's own poses); default:
    one column with the graph's own poses.  Each column has its own energy colour scale and
    colour bar (so every map shows its own worst residuals in red), unless ``energy_range``
    (see :func:`residual_energy_range`) puts them all on one scale.  The oblique views share one
    height exaggeration ``z_scale`` (default: fitted to all the sets).  One legend for the
    figure sits at the bottom; every title carries the energy per constraint.
    """
    cols = list(poses) if poses is not None else [None]
    resolved = [_poses(graph, *(p if p is not None else (None, None))) for p in cols]
    n = len(cols)
    views = 1 if graph.is_2d else 2
    # one pose set: views side by side; several: one column per set, one row per view
    nrows, ncols = (1, views) if n == 1 else (views, n)
    fig = _new_figure((6.5 * ncols, 6.0 * nrows + 0.6))
    # one height exaggeration for every oblique panel, so that they compare
    if z_scale is None:
        z_scale = _auto_z_scale(np.concatenate([t for _, t in resolved]))
    for k, (r, t) in enumerate(resolved):
        title = titles[k] if titles is not None and k < len(titles) else None
        e_range = energy_range
        if residuals and e_range is None:
            e_range = _energy_range([_graph_energies(graph, r, t)])
        ax = fig.add_subplot(nrows, ncols, 1 + k)
        plot_graph(graph, r, t, ax=ax, residuals=residuals, energy_range=e_range,
                   colorbar=False, title=title, legend=False, energy_in_title=energy_in_title)
        column = [ax]
        if views == 2:
            ax3 = fig.add_subplot(nrows, ncols, 2 + k if n == 1 else 1 + n + k)
            plot_graph_3d(graph, r, t, ax=ax3, residuals=residuals, energy_range=e_range,
                          z_scale=z_scale, title=title, legend=False,
                          energy_in_title=energy_in_title)
            column.append(ax3)
        # a colour bar per column, or one for the figure when the scale is shared
        if residuals and e_range is not None and (energy_range is None or k == n - 1):
            axes = column if energy_range is None else fig.axes[:]
            _colorbar(fig, _energy_norm(e_range, np.zeros(0)), axes)
    handles = legend_handles(graph, residuals)
    # about two entries per panel across: wider figures get fewer legend rows
    fig.legend(handles=handles, loc="outside lower center",
               ncols=min(len(handles), 2 * ncols + (ncols > 1)), fontsize="small",
               frameon=False)
    return fig


def height_scale(poses: Sequence[tuple[FloatArray, FloatArray]]) -> float:
    """The oblique views' height exaggeration fitted to several pose sets (see
    :func:`plot_graph_3d`), to share between separate figures."""
    return _auto_z_scale(np.concatenate([np.asarray(t, np.float64) for _, t in poses]))


def residual_energy_range(graph: PoseGraph,
                          poses: Sequence[tuple[FloatArray, FloatArray]]) -> tuple[float, float]:
    """A colour range covering the constraint energies of ``graph`` at every pose set, so that
    separate figures (before / after) use the same scale."""
    return _energy_range([_graph_energies(graph, r, t) for r, t in poses])


def energy_figure(results: Mapping[str, SolveResult], *, title: str | None = None) -> Figure:
    """A figure with :func:`plot_energy` of ``results``."""
    ax = plot_energy(results, title=title)
    fig = ax.figure
    assert fig is not None
    return fig  # type: ignore[return-value]


#: Largest resolution :func:`save_figure` renders: a 2x2-panel figure (13 x 12 in) at 600 dpi
#: is ~7800 x 7200 pixels, ~225 MB of RGBA (``plot --dpi 100000`` ran out of memory).
MAX_DPI = 600


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 150) -> None:
    """Write ``fig`` to ``path`` under the output rules of :mod:`hybridpgo._output` (a temporary
    file renamed into place, symbolic links written through, FIFOs written into); the format
    comes from the extension (``.png`` when there is none).

    Raises
    ------
    HybridPGOError
        For an unsupported extension, ``dpi`` outside 1..:data:`MAX_DPI`, or when the file
        cannot be written.
    """
    if not 1 <= dpi <= MAX_DPI:
        raise HybridPGOError(f"{os.fspath(path)}: dpi must be in 1..{MAX_DPI}, got {dpi}")
    _require_matplotlib()
    name = os.fspath(path)
    ext = os.path.splitext(name)[1].lower().lstrip(".") or "png"
    supported = fig.canvas.get_supported_filetypes()
    if ext not in supported:
        raise HybridPGOError(f"{name}: cannot write a figure as .{ext}; supported: "
                             + ", ".join(sorted(supported)))
    try:
        with Outputs([name]) as out:
            fig.savefig(out.temp(name), format=ext, dpi=dpi)
            out.commit()
    except (FormatError, OSError) as exc:
        why = (exc.problem.removeprefix("cannot write the file: ") if isinstance(exc, FormatError)
               else exc.strerror or str(exc))
        raise HybridPGOError(f"{name}: cannot write the figure: {why}") from exc
