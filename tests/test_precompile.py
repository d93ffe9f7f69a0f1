"""Compiling on two cores (hybridpgo._precompile): a helper process fills
Numba's on-disk cache, this process loads what it saved instead of compiling it again, and a
helper that fails, is killed or outlives its parent changes nothing but the time.

Every check that compiles runs in a fresh interpreter with its own ``NUMBA_CACHE_DIR`` (this
test process may have compiled the kernels already).
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import time

import pytest

import hybridpgo
from hybridpgo import _precompile

SRC = pathlib.Path(hybridpgo.__file__).resolve().parent.parent
TESTS = pathlib.Path(__file__).resolve().parent

TOY = '''
import time
from hybridpgo._numba import kernel


@kernel
def g(x):
    return x + 1.0


@kernel
def f(x):
    return 2.0 * g(x)


def warm():
    f(1.0)


def boom():
    raise RuntimeError("helper failure")


def sleepy():
    time.sleep(60)
'''

#: The helper compiles ``groups`` (argv[1], comma-separated); then this process calls f.
#: argv[2]: "join" (wait for the helper), "kill" (SIGKILL it first), "none" (no helper).
SCRIPT = """
import json, os, signal, sys, time
from hybridpgo import _precompile
from hybridpgo._numba import compile_status
groups, how = sys.argv[1].split(","), sys.argv[2]
helper = None if how == "none" else _precompile.start(groups, force=True)
ok = None
if how == "join":
    ok = helper.join(120)
elif how == "kill":
    time.sleep(0.5)
    os.kill(helper.proc.pid, signal.SIGKILL)
    helper.proc.wait()
from toypkg.a import f
t0 = time.perf_counter()
value = f(1.0)
out = {"value": value, "compiled": compile_status().compiled, "ok": ok,
       "done": sorted(helper.done) if helper else [], "seconds": time.perf_counter() - t0}
_precompile.stop()
out["alive"] = helper is not None and helper.proc.poll() is None
print(json.dumps(out))
"""


def _env(tmp_path: pathlib.Path) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(SRC)]),
               NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("NUMBA_DISABLE_JIT", None)
    return env


def _toy(tmp_path: pathlib.Path) -> None:
    pkg = tmp_path / "toypkg"
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(TOY)


def _run(tmp_path: pathlib.Path, groups: str, how: str) -> dict[str, object]:
    import json

    _toy(tmp_path)
    out = subprocess.run([sys.executable, "-c", SCRIPT, groups, how], env=_env(tmp_path),
                         check=True, capture_output=True, text=True, timeout=300).stdout
    result: dict[str, object] = json.loads(out.splitlines()[-1])
    return result


def test_this_process_loads_what_the_helper_compiled(tmp_path: pathlib.Path) -> None:
    out = _run(tmp_path, "toypkg.a:warm", "join")
    assert out["ok"] is True
    assert {"toypkg.a.f", "toypkg.a.g"} <= set(out["done"])  # type: ignore[arg-type]
    assert (out["value"], out["compiled"], out["alive"]) == (4.0, 0, False)
    # the control: without a helper, a fresh cache compiles
    out = _run(tmp_path / "control", "toypkg.a:warm", "none")
    assert out["value"] == 4.0 and out["compiled"] > 0  # type: ignore[operator]


@pytest.mark.parametrize(("groups", "how"), [("toypkg.a:boom", "join"),
                                              ("toypkg.a:sleepy", "kill")])
def test_a_failed_or_killed_helper_changes_nothing_but_the_time(
        tmp_path: pathlib.Path, groups: str, how: str) -> None:
    out = _run(tmp_path, groups, how)
    assert out["ok"] in (False, None)
    assert out["value"] == 4.0 and out["compiled"] > 0  # type: ignore[operator]
    assert out["alive"] is False
    assert out["seconds"] < 30  # type: ignore[operator]  # no wait for a dead helper


PARENT = """
import sys, time
from hybridpgo import _precompile
helper = _precompile.start(["toypkg.a:sleepy"], force=True)
print(helper.proc.pid, flush=True)
time.sleep(1.0)
import os
os._exit(0)  # no atexit handler: only the closed pipe tells the helper
"""


def _running(pid: int) -> bool:
    try:
        state = pathlib.Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in state


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_helper_ends_with_its_parent(tmp_path: pathlib.Path) -> None:
    _toy(tmp_path)
    out = subprocess.run([sys.executable, "-c", PARENT], env=_env(tmp_path), check=True,
                         capture_output=True, text=True, timeout=60).stdout
    pid = int(out.split()[0])
    deadline = time.monotonic() + 20
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _running(pid)


def test_waits_for_a_kernel_the_helper_is_compiling() -> None:
    """The protocol: ``start NAME`` ... ``done NAME`` on the helper's stdout."""
    code = ("import sys, time; print('start m.k', flush=True); time.sleep(1.0); "
            "print('done m.k', flush=True); print('end', flush=True); sys.stdin.read()")
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE)
    helper = _precompile.Helper(proc, ["m"])
    try:
        deadline = time.monotonic() + 20
        while not helper.compiling("m.k") and time.monotonic() < deadline:
            time.sleep(0.01)
        assert helper.compiling("m.k") and not helper.compiling("m.other")
        assert helper.wait_for("m.k", timeout=20)
        assert helper.waited > 0.3 and "m.k" in helper.done
        assert not helper.wait_for("m.other", timeout=20)  # never started: no wait
    finally:
        helper.stop()
    assert proc.poll() is not None


def test_off_unless_asked_under_pytest_or_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    monkeypatch.delenv(_precompile.ENV, raising=False)
    assert not _precompile.enabled()  # PYTEST_CURRENT_TEST is set
    assert _precompile.start(["finish"]) is None
    monkeypatch.delenv("PYTEST_CURRENT_TEST")
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setattr(_precompile, "_idle_cores", lambda: 1.2)
    assert _precompile.enabled()
    monkeypatch.setattr(_precompile, "_idle_cores", lambda: 0.5)  # a busy machine
    assert not _precompile.enabled()
    monkeypatch.setenv("CI", "true")
    assert not _precompile.enabled()
    monkeypatch.setenv(_precompile.ENV, "1")
    assert _precompile.enabled()
    monkeypatch.setenv(_precompile.ENV, "0")
    monkeypatch.delenv("CI")
    assert not _precompile.enabled()


REAL = """
import json, sys
import numpy as np
from hybridpgo import _precompile
from hybridpgo._numba import compile_status
helper = _precompile.start(sys.argv[1].split(","), force=True)
ok = helper.join(600)
from hybridpgo.io import read_graph
from hybridpgo.energy import energy
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.tree import build_tree, global_poses
from hybridpgo.initialization import initial_locals
graph = read_graph(sys.argv[2])
before = compile_status().compiled
tree = build_tree(graph)
for init in ("file", "chordal"):
    rot, trans = initial_locals(graph, tree, init)
    e = energy(graph, *global_poses(tree, np.array(rot), np.array(trans)))
finish = compile_status().compiled - before
result = solve_exact(graph)
print(json.dumps({"ok": ok, "finish": finish,
                  "exact": compile_status().compiled - before - finish,
                  "energy": float(result.energy_history[-1])}))
"""


@pytest.mark.slow  # about 15 s on a quiet machine: the helper compiles both groups
def test_the_real_groups_compile_what_a_solve_loads(tmp_path: pathlib.Path) -> None:
    """The groups' three-pose graph gives the kernels the argument types of a real solve:
    after the helper, the steps after the sweep and the exact solver compile nothing."""
    import json

    graph = TESTS / "data" / "tinyGrid3D.g2o"
    out = json.loads(subprocess.run(
        [sys.executable, "-c", REAL, "finish,exact,starts,exact-solve", str(graph)],
        env=_env(tmp_path), check=True, capture_output=True, text=True,
        timeout=900).stdout.splitlines()[-1])
    assert out["ok"] is True
    assert (out["finish"], out["exact"]) == (0, 0)
    assert out["energy"] >= 0.0


def test_a_warm_cache_is_told_by_the_first_group_only(monkeypatch):
    """A later group's probe that the main process never compiles (and a helper ended with it
    never reached) must not make every warm run start a helper."""
    from hybridpgo import _numba, _precompile

    cached = {"hybridpgo._tree_kernels:globals_from_locals": True,
              "hybridpgo._cost:constraint_energies": True}
    monkeypatch.setattr(_precompile, "_resolve", lambda ref: ref)
    monkeypatch.setattr(_numba, "is_cached", lambda ref: cached.get(ref, False))
    assert not _precompile._cold(["finish", "exact-solve"])  # exact-solve's probe: not cached
    cached["hybridpgo._cost:constraint_energies"] = False
    assert _precompile._cold(["finish", "exact-solve"])


def test_every_group_names_kernels_that_exist() -> None:
    """Each group's cold/warm probes resolve to cached kernels: a probe that names a moved or
    renamed kernel made the first run on a fresh machine fail (AttributeError) before any
    kernel was compiled."""
    for name, (fn, probes) in _precompile.GROUPS.items():
        assert callable(fn), name
        assert probes, name
        for ref in probes:
            obj = _precompile._resolve(ref)
            assert hasattr(obj, "_cache"), f"{name}: {ref} is not a cached kernel"
