"""Plots (``hybridpgo.plot``): geometry of the drawn residuals, colours, atomic saving, and the
error when matplotlib is missing.  Figures use the Agg canvas; nothing is shown."""

from __future__ import annotations

import builtins
import os
from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph
from tolerances import FLOAT64_IDENTITY

from hybridpgo import HybridPGOError, PoseGraph, read_graph
from hybridpgo.energy import constraint_energies

pytest.importorskip("matplotlib")

from matplotlib.axes import Axes
from matplotlib.colors import to_rgba

from hybridpgo import plot

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def consistent_graph(rng: np.random.Generator, n: int = 12, gps: bool = False) -> PoseGraph:
    """A chain plus loops whose measurements match its vertices exactly (energy 0)."""
    g, rot, trans = random_graph(rng, n=n, extra=5)
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    zr = np.swapaxes(rot[a], 1, 2) @ rot[b]
    zt = np.einsum("nji,nj->ni", rot[a], trans[b] - trans[a])
    kw = {}
    if gps:
        kw = {"gps_nodes": np.array([0, n // 2], np.int32), "gps_positions": trans[[0, n // 2]],
              "gps_information": np.tile(np.eye(3), (2, 1, 1))}
    return PoseGraph(node_ids=g.node_ids, rotations=rot, translations=trans,
                     edge_nodes=g.edge_nodes, edge_rotations=zr, edge_translations=zt,
                     edge_information=g.edge_information, **kw)


def line_points(ax: Axes) -> list[np.ndarray]:
    """(k, 2) points of every NaN-separated line on ``ax`` (the pose markers excluded)."""
    out = []
    for line in ax.get_lines():
        if line.get_linestyle() == "None":
            continue
        xy = np.column_stack([line.get_xdata(), line.get_ydata()]).astype(float)
        out.append(xy)
    return out


def segments_of(xy: np.ndarray) -> np.ndarray:
    """(k, 2, 2) segments from a NaN-separated point list (start, end, nan, ...)."""
    return xy.reshape(-1, 3, 2)[:, :2]


def test_residuals_are_desired_to_actual(rng: np.random.Generator) -> None:
    """Move one pose: exactly its constraints get a residual, from X_a·Z_c to the moved pose."""
    g = consistent_graph(rng)
    moved = 5
    trans = np.array(g.translations)
    trans[moved] += [1.0, -2.0, 0.5]
    ax = plot.plot_graph(g, g.rotations, trans, colorbar=False)
    e_rel, _ = constraint_energies(g, g.rotations, trans)
    touching = (g.edge_nodes == moved).any(axis=1)
    assert np.all(e_rel[~touching] < FLOAT64_IDENTITY)
    lines = line_points(ax)
    trajectory = segments_of(lines[0])
    residual = np.concatenate([segments_of(xy) for xy in lines[1:]])
    assert trajectory.shape[0] == np.count_nonzero(np.abs(np.diff(g.edge_nodes, axis=1)) == 1)
    assert residual.shape[0] == g.num_edges
    lengths = np.linalg.norm(residual[:, 1] - residual[:, 0], axis=1)
    # edges into the moved pose end at its new position, from where it should be (the old one)
    into = g.edge_nodes[:, 1] == moved
    ends = residual[np.all(residual[:, 1] == trans[moved, :2], axis=1)]
    assert ends.shape[0] == np.count_nonzero(into)
    np.testing.assert_allclose(ends[:, 0], np.tile(g.translations[moved, :2], (ends.shape[0], 1)),
                               rtol=0, atol=FLOAT64_IDENTITY * 100)
    assert np.count_nonzero(lengths > 1e-9) == np.count_nonzero(touching)


def test_highest_energy_is_bright_red_and_on_top(rng: np.random.Generator) -> None:
    g, _, _ = random_graph(rng, n=15, extra=8, noise=0.3)
    ax = plot.plot_graph(g, colorbar=False)
    residual_lines = [ln for ln in ax.get_lines() if ln.get_linestyle() != "None"][1:]
    top = max(residual_lines, key=lambda ln: ln.get_zorder())
    bottom = min(residual_lines, key=lambda ln: ln.get_zorder())
    assert np.allclose(to_rgba(top.get_color())[:3], to_rgba(plot.RESIDUAL_COLORS[-1])[:3],
                       atol=0.05)
    # the lowest level is brown: red channel well below the top's, no blue
    assert to_rgba(bottom.get_color())[0] < to_rgba(top.get_color())[0]
    # the top line holds the constraint of highest energy
    e_rel, _ = constraint_energies(g)
    c = int(np.argmax(e_rel))
    a = g.edge_nodes[c, 0]
    desired = g.rotations[a] @ g.edge_translations[c] + g.translations[a]
    seg = segments_of(np.column_stack([top.get_xdata(), top.get_ydata()]))
    assert np.any(np.all(np.abs(seg[:, 0] - desired[:2]) < 1e-9, axis=1))


def test_gps_residuals_are_blue(rng: np.random.Generator) -> None:
    g = consistent_graph(rng, gps=True)
    trans = np.array(g.translations)
    trans[g.gps_nodes[1]] += [3.0, 0.0, 0.0]
    ax = plot.plot_graph(g, g.rotations, trans)
    blue = [ln for ln in ax.get_lines() if ln.get_color() == plot.GPS_COLOR]
    assert len(blue) == 1
    seg = segments_of(np.column_stack([blue[0].get_xdata(), blue[0].get_ydata()]))
    np.testing.assert_allclose(seg[:, 0], g.gps_positions[:, :2], rtol=0, atol=0)
    np.testing.assert_allclose(seg[:, 1], trans[g.gps_nodes, :2], rtol=0, atol=0)


def test_plot_graph_into_given_axes_returns_them(data_dir: Path) -> None:
    g = read_graph(data_dir / "tinyGrid3D.g2o")
    fig = plot._new_figure()
    ax = fig.add_subplot()
    assert plot.plot_graph(g, ax=ax, residuals=False) is ax
    assert plot.plot_graph_3d(g, ax=fig.add_subplot()) is not ax
    assert ax.get_xlabel() == "x [m]"


def test_oblique_projection() -> None:
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    top = plot.oblique_projection(pts, azim=-90.0, elev=90.0)  # camera south, looking down
    np.testing.assert_allclose(top, [[1, 0], [0, 1], [0, 0]], rtol=0, atol=FLOAT64_IDENTITY)
    side = plot.oblique_projection(pts, azim=-90.0, elev=0.0, z_scale=2.0)  # from the south
    np.testing.assert_allclose(side, [[1, 0], [0, 0], [0, 2]], rtol=0, atol=FLOAT64_IDENTITY)


def test_plot_graph_3d_title_and_scale(data_dir: Path) -> None:
    g = read_graph(data_dir / "smallGrid3D.g2o")
    ax = plot.plot_graph_3d(g, title="grid", z_scale=1.0)
    name, energy_line, view = ax.get_title().split("\n")
    assert name == "grid" and energy_line.startswith("E/c ") and view.startswith("oblique view")
    assert "heights x1" in ax.get_title()


def test_titles_carry_the_energy_per_constraint(rng: np.random.Generator) -> None:
    from hybridpgo.energy import energy

    g, _, _ = random_graph(rng, n=10, extra=5, noise=0.3)
    e = energy(g)
    expected = f"E/c {e / g.num_constraints:.4g}  (E {e:.4g}, {g.num_constraints} constraints)"
    assert plot.energy_title(g) == expected
    assert plot.plot_graph(g, title="t").get_title() == "t\n" + expected
    assert plot.plot_graph(g).get_title() == expected
    assert plot.plot_graph(g, title="t", energy_in_title=False).get_title() == "t"


def test_legend_and_start_end_markers(rng: np.random.Generator) -> None:
    g = consistent_graph(rng, gps=True)
    ax = plot.plot_graph(g)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[0].startswith("trajectory") and labels[1].startswith("residual")
    assert labels[2].startswith("GPS residual")
    assert labels[3:] == [f"start (pose {g.node_ids[0]})", f"end (pose {g.node_ids[-1]})"]
    start = next(ln for ln in ax.get_lines() if ln.get_marker() == plot.START_STYLE["marker"])
    end = next(ln for ln in ax.get_lines() if ln.get_marker() == plot.END_STYLE["marker"])
    np.testing.assert_array_equal(np.column_stack([start.get_xdata(), start.get_ydata()]),
                                  g.translations[:1, :2])
    np.testing.assert_array_equal(np.column_stack([end.get_xdata(), end.get_ydata()]),
                                  g.translations[-1:, :2])
    # no GPS: no GPS entry; no residuals: no residual entry
    g0, _, _ = random_graph(rng, n=6, extra=2)
    labels = [t.get_text() for t in plot.plot_graph(g0, residuals=False).get_legend().get_texts()]
    assert [x.split()[0] for x in labels] == ["trajectory", "start", "end"]
    assert plot.plot_graph(g0, legend=False).get_legend() is None


def test_scale_bar_of_the_oblique_view(data_dir: Path) -> None:
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    assert [plot._nice_length(s) for s in (100.0, 47.0, 0.3, 5e4)] == [20.0, 5.0, 0.05, 1e4]
    assert [plot._fmt_length(v) for v in (20.0, 0.05, 1e4)] == ["20 m", "5 cm", "10 km"]
    g = read_graph(data_dir / "smallGrid3D.g2o")
    ax = plot.plot_graph_3d(g)
    [bar] = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    screen_x = plot.oblique_projection(g.translations)[:, 0]
    length = plot._nice_length(float(np.ptp(screen_x)))
    assert bar.size_bar.get_children()[0].get_width() == pytest.approx(length)
    assert bar.txt_label.get_text() == plot._fmt_length(length)
    assert not [a for a in plot.plot_graph_3d(g, scale_bar=False).artists
                if isinstance(a, AnchoredSizeBar)]


def test_isam_graph_is_drawn_at_the_tree_initialization(tmp_path: Path, data_dir: Path) -> None:
    from hybridpgo.io import write_graph

    isam = tmp_path / "t.txt"
    write_graph(read_graph(data_dir / "tinyGrid3D.g2o"), isam, "isam")
    g = read_graph(isam)
    ax = plot.plot_graph(g, colorbar=False)
    markers = next(ln for ln in ax.get_lines() if ln.get_linestyle() == "None")
    assert np.ptp(np.asarray(markers.get_xdata(), float)) > 0  # not all at the identity


def test_plot_energy(rng: np.random.Generator) -> None:
    from hybridpgo.solvers import optimize

    g, _, _ = random_graph(rng, n=10, extra=5)
    results = {"hybrid": optimize(g, "hybrid", sweeps=4, polish=True),
               "exact": optimize(g, "exact")}
    ax = plot.plot_energy(results)
    assert ax.get_yscale() == "log"
    labels = [ln.get_label() for ln in ax.get_lines()]
    assert labels == ["hybrid", "hybrid: exact polish", "exact"]
    sweeps = ax.get_lines()[0]
    r = results["hybrid"]
    np.testing.assert_array_equal(sweeps.get_ydata(),
                                  r.energy_history[:r.iterations + 1] / r.num_constraints)


def test_save_figure_is_atomic_png(tmp_path: Path, data_dir: Path) -> None:
    fig = plot.graph_figure(read_graph(data_dir / "tinyGrid3D.g2o"), titles=["tiny"])
    path = tmp_path / "fig.png"
    plot.save_figure(fig, path)
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert os.listdir(tmp_path) == ["fig.png"]
    with pytest.raises(HybridPGOError, match=r"cannot write a figure as \.xyz"):
        plot.save_figure(fig, tmp_path / "fig.xyz")
    with pytest.raises(HybridPGOError, match="cannot write the figure"):
        plot.save_figure(fig, tmp_path / "missing" / "fig.png")
    assert os.listdir(tmp_path) == ["fig.png"]


def test_graph_figure_layout(data_dir: Path) -> None:
    g3 = read_graph(data_dir / "tinyGrid3D.g2o")
    fig = plot.graph_figure(g3, [None, (g3.rotations, g3.translations)], titles=["a", "b"])
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert len(panels) == 4  # 2 pose sets x (top-down, oblique)
    oblique = [ax.get_title() for ax in panels if "oblique" in ax.get_title()]
    assert len(oblique) == 2
    assert oblique[0].split("heights")[1] == oblique[1].split("heights")[1]  # one z scale
    with pytest.warns(UserWarning, match="EQUIV"):
        g2 = read_graph(data_dir / "w100_toro.graph")
    fig = plot.graph_figure(g2, residuals=False)
    assert len(fig.axes) == 1  # 2D: top-down only, no colour bar without residuals


def _colorbar_ranges(fig: object) -> list[tuple[float, float]]:
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]  # type: ignore[attr-defined]
    return [(ax._colorbar.norm.vmin, ax._colorbar.norm.vmax) for ax in bars]


def test_each_map_has_its_own_colour_scale_by_default(rng: np.random.Generator) -> None:
    """An optimized map shows its own worst residuals in red, not the darkest brown of the
    initial map's scale."""
    g = consistent_graph(rng)
    rot = np.array(g.rotations)
    before = (rot, g.translations + rng.normal(scale=1.0, size=(g.num_nodes, 3)))
    after = (rot, g.translations + rng.normal(scale=0.01, size=(g.num_nodes, 3)))
    before_e = constraint_energies(g, *before)[0]
    after_e = constraint_energies(g, *after)[0]
    assert before_e.max() > 100 * after_e.max()
    fig = plot.graph_figure(g, [before, after], titles=["before", "after"])
    ranges = _colorbar_ranges(fig)
    assert len(ranges) == 2
    assert ranges[0][1] == pytest.approx(before_e.max(), rel=FLOAT64_IDENTITY)
    assert ranges[1][1] == pytest.approx(after_e.max(), rel=FLOAT64_IDENTITY)
    # a shared range: one colour bar for the figure
    shared = plot.residual_energy_range(g, [before, after])
    fig = plot.graph_figure(g, [before, after], energy_range=shared)
    assert _colorbar_ranges(fig) == [shared]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[0].startswith("trajectory") and labels[-1].startswith("end")


def test_shared_energy_range(rng: np.random.Generator) -> None:
    g, _, _ = random_graph(rng, n=10, extra=5, noise=0.3)
    lo, hi = plot.residual_energy_range(g, [(g.rotations, g.translations)])
    e_rel, _ = constraint_energies(g)
    assert hi == pytest.approx(float(e_rel.max()), rel=FLOAT64_IDENTITY)
    assert lo >= hi * 10.0 ** -plot.ENERGY_DECADES


def test_missing_matplotlib_names_the_extra(monkeypatch: pytest.MonkeyPatch,
                                            data_dir: Path) -> None:
    real_import = builtins.__import__

    def no_matplotlib(name: str, *args: object, **kwargs: object) -> object:
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    g = read_graph(data_dir / "tinyGrid3D.g2o")
    with pytest.raises(HybridPGOError, match=r"pip install hybridpgo\[plot\]"):
        plot.plot_graph(g)


def test_large_graph_draws_in_seconds(tmp_path: Path) -> None:
    """~50 000 poses (a long noisy chain with loops) draw and save in a few seconds."""
    rng = np.random.default_rng(0)
    n, loops = 50_000, 10_000
    yaw = np.cumsum(rng.normal(scale=0.05, size=n))
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(yaw)
    rot[:, 0, 1], rot[:, 1, 0] = -np.sin(yaw), np.sin(yaw)
    rot[:, 2, 2] = 1.0
    trans = np.zeros((n, 3))
    trans[:, 0] = np.cumsum(np.cos(yaw))
    trans[:, 1] = np.cumsum(np.sin(yaw))
    a = np.concatenate([np.arange(n - 1), rng.integers(0, n // 2, loops)])
    b = np.concatenate([np.arange(1, n), rng.integers(n // 2, n, loops)])
    m = a.shape[0]
    g = PoseGraph(node_ids=np.arange(n), rotations=rot, translations=trans,
                  edge_nodes=np.column_stack([a, b]), edge_rotations=np.tile(np.eye(3), (m, 1, 1)),
                  edge_translations=np.tile([1.0, 0.0, 0.0], (m, 1)),
                  edge_information=np.tile(np.eye(6), (m, 1, 1)))
    fig = plot.graph_figure(g)
    # what keeps 60k residuals fast is drawing them as a few collections, not one artist per
    # edge (speed itself belongs in benchmarks/, not in a timed test: the machine is shared)
    for ax in fig.axes:
        assert len(ax.lines) + len(ax.collections) < m / 100  # measured: at most 50 (bins)
    plot.save_figure(fig, tmp_path / "big.png")
    assert (tmp_path / "big.png").stat().st_size > 0

