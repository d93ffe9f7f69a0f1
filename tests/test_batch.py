"""``hybridpgo batch``: many optimizations on Dask (optional extra ``hybridpgo[dask]``)."""

from __future__ import annotations

import builtins
import csv
import json
import os
from pathlib import Path

import pytest
from tolerances import FLOAT64_IDENTITY

from hybridpgo import energy, optimize, read_graph
from hybridpgo.cli import main

distributed = pytest.importorskip("distributed")


@pytest.fixture
def bad_g2o(tmp_path: Path) -> Path:
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0\n")
    return path


@pytest.fixture(scope="module", autouse=True)
def _compiled(request: pytest.FixtureRequest) -> None:
    """Compile the kernels here once, so the workers load them from Numba's disk cache
    instead of compiling them side by side."""
    g = read_graph(Path(request.config.rootpath) / "tests" / "data" / "tinyGrid3D.g2o")
    optimize(g, "hybrid", sweeps=1, polish=True)


def read_summary(out_dir: Path) -> tuple[list[dict[str, str]], list[dict[str, object]]]:
    with open(out_dir / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return rows, json.loads((out_dir / "summary.json").read_text())["jobs"]


def test_batch_on_a_local_cluster_of_two_workers(capsys: pytest.CaptureFixture[str],
                                                  data_dir: Path, tmp_path: Path,
                                                  bad_g2o: Path) -> None:
    out = tmp_path / "out"
    inputs = [data_dir / "tinyGrid3D.g2o", data_dir / "w100_toro.graph", bad_g2o]
    with pytest.warns(UserWarning, match="EQUIV"):  # w100's EQUIV lines, read here to check
        w100 = read_graph(inputs[1])
    code = main(["batch", *map(str, inputs), "-o", str(out), "--workers", "2",
                 "--grid", "sweeps=2,4", "--grid", "polish=true"])
    text, err = capsys.readouterr()
    assert code == 3, err  # one input failed, the others ran
    rows, jobs = read_summary(out)
    assert [(Path(r["input"]).name, r["options"], r["status"]) for r in rows] == [
        ("tinyGrid3D.g2o", "sweeps=2 polish=True", "ok"),
        ("tinyGrid3D.g2o", "sweeps=4 polish=True", "ok"),
        ("w100_toro.graph", "sweeps=2 polish=True", "ok"),
        ("w100_toro.graph", "sweeps=4 polish=True", "ok"),
        ("bad.g2o", "sweeps=2 polish=True", "failed"),
        ("bad.g2o", "sweeps=4 polish=True", "failed")]
    assert [j["options"] for j in jobs[:2]] == [{"sweeps": 2, "polish": True},
                                               {"sweeps": 4, "polish": True}]
    for row, job in zip(rows, jobs, strict=True):
        assert row["output"] == job["output"]
        if row["status"] == "ok":
            # oracle: the reported energy is the energy of the file the job wrote
            written = read_graph(row["output"])
            assert float(row["energy_after"]) == pytest.approx(energy(written),
                                                               rel=FLOAT64_IDENTITY)
            assert job["energy_after"] == float(row["energy_after"])
            assert float(row["time_s"]) > 0 and row["error"] == ""
        else:
            assert "FormatError" in row["error"] and "bad.g2o:2:" in row["error"]
            assert not os.path.exists(row["output"])
    assert read_graph(rows[2]["output"]).is_2d and rows[2]["output"].endswith(".graph")
    assert read_graph(rows[2]["output"]).num_nodes == w100.num_nodes
    assert "bad.g2o" in text and "failed" in text and "wrote" in text
    assert "\r" not in err  # not a terminal: no progress drawn


def test_batch_on_a_running_scheduler(capsys: pytest.CaptureFixture[str], data_dir: Path,
                                      tmp_path: Path) -> None:
    tiny = data_dir / "tinyGrid3D.g2o"
    with distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1,
                                  dashboard_address=None) as cluster:
        code = main(["batch", str(tiny), "-o", str(tmp_path / "out"), "--solver", "exact",
                     "--grid", "max_iterations=1,50", "--scheduler", cluster.scheduler_address,
                     "--json", "-q"])
    text, err = capsys.readouterr()
    assert code == 0, err
    assert err == ""
    jobs = json.loads(text)["jobs"]
    graph = read_graph(tiny)
    assert [j["solver_status"] for j in jobs] == ["max_iterations", "converged"]
    for job, iters in zip(jobs, (1, 50), strict=True):
        ref = optimize(graph, "exact", max_iterations=iters)  # the same library call, here
        assert job["status"] == "ok" and job["solver_status"] == ref.status.value
        assert job["energy_after"] == pytest.approx(ref.final_energy, rel=FLOAT64_IDENTITY)


@pytest.mark.parametrize(("extra", "message"), [
    (["--grid", "nonsense=1"], "'nonsense' is not an option of the hybrid solver"),
    (["--grid", "sweeps=-1"], "invalid solver option: sweeps must be"),
    (["--grid", "sweeps"], "expected KEY=V1,V2"),
    (["--grid", "sweeps=1", "--grid", "sweeps=2"], "sweeps is given twice"),
    (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "--workers sizes the local"),
])
def test_bad_arguments_run_nothing(capsys: pytest.CaptureFixture[str], data_dir: Path,
                                   tmp_path: Path, extra: list[str], message: str) -> None:
    code = main(["batch", str(data_dir / "tinyGrid3D.g2o"), "-o", str(tmp_path / "out"),
                 *extra])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.startswith("hybridpgo: error: ") and message in err
    assert os.listdir(tmp_path) == []


def test_missing_input_and_colliding_outputs(capsys: pytest.CaptureFixture[str],
                                             data_dir: Path, tmp_path: Path) -> None:
    code = main(["batch", str(tmp_path / "nope.g2o"), "-o", str(tmp_path / "out")])
    assert code == 2 and "nope.g2o: no such file" in capsys.readouterr().err
    (tmp_path / "a").mkdir()
    copy = tmp_path / "a" / "tinyGrid3D.g2o"
    copy.write_bytes((data_dir / "tinyGrid3D.g2o").read_bytes())
    code = main(["batch", str(data_dir / "tinyGrid3D.g2o"), str(copy), "-o",
                 str(tmp_path / "out")])
    assert code == 2 and "would both write" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_missing_dask_names_the_extra(monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture[str], data_dir: Path,
                                      tmp_path: Path) -> None:
    real_import = builtins.__import__

    def no_dask(name: str, *args: object, **kwargs: object) -> object:
        if name.split(".")[0] in ("dask", "distributed"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_dask)
    code = main(["batch", str(data_dir / "tinyGrid3D.g2o"), "-o", str(tmp_path / "out")])
    assert code == 2
    assert r"pip install hybridpgo[dask]" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_batch_never_overwrites_an_input(capsys: pytest.CaptureFixture[str], tiny: Path,
                                         tmp_path: Path) -> None:
    """Inputs and outputs are compared by identity (device and inode), not by path text."""
    d = tmp_path / "D"
    d.mkdir()
    x = d / "x.g2o"
    x.write_bytes(tiny.read_bytes())
    (tmp_path / "L").symlink_to(d)  # the output directory through a link
    (tmp_path / "F").mkdir()
    (tmp_path / "F" / "x.g2o").symlink_to(x)  # the input through a link
    e = tmp_path / "E"
    e.mkdir()
    table = e / "summary.csv"  # an input where the summary goes
    table.write_bytes(tiny.read_bytes())
    saved = x.read_bytes()
    for argv in ([str(tmp_path / "L" / "x.g2o"), "-o", str(d)],
                 [str(x), "-o", str(tmp_path / "L")],
                 [str(tmp_path / "F" / "x.g2o"), "-o", str(d)],
                 [str(table), "-o", str(e)]):
        code = main(["batch", *argv, "-q"])
        err = capsys.readouterr().err
        assert code == 2, err
        assert "would overwrite this input" in err and "Traceback" not in err
    assert x.read_bytes() == saved and table.read_bytes() == saved
    assert sorted(p.name for p in d.iterdir()) == ["x.g2o"]


def test_an_interrupted_batch_says_what_it_kept(capsys: pytest.CaptureFixture[str], tiny: Path,
                                                tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    import hybridpgo.cli.batch as batch

    def interrupted(jobs, *, finished, **kwargs):  # type: ignore[no-untyped-def]
        finished.append(batch.run_job(jobs[0]))  # one job done, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(batch, "run_on_dask", interrupted)
    out = tmp_path / "out"
    code = main(["batch", str(tiny), "-o", str(out), "--grid", "sweeps=1,2", "-q"])
    err = capsys.readouterr().err
    assert code == 130, err
    first = out / "tinyGrid3D__sweeps-1.g2o"
    assert first.exists()
    assert (f"batch interrupted after 1 of 2 job(s) finished; their 1 output(s) are kept: "
            f"{first}; the summary was not written") in err
    assert not (out / "summary.csv").exists()
