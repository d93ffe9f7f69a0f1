"""Numba's on-disk cache: a kernel whose callee changed in another file is recompiled, never
loaded stale (hybridpgo._numba's package stamp), and an unchanged one loads without compiling."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import hybridpgo

SRC = pathlib.Path(hybridpgo.__file__).resolve().parent.parent

SCRIPT = """
import pathlib, sys
import hybridpgo._numba as nb
nb.STAMP_ROOTS.append(pathlib.Path(sys.argv[1]).resolve())
from kpkg.a import f
print(f(1.0), nb.compile_status().compiled)
"""


def _run(root: pathlib.Path) -> tuple[float, int]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root.parent), str(SRC)]))
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(root)], env=env, check=True,
                         capture_output=True, text=True).stdout.split()
    return float(out[0]), int(out[1])


def test_cache_is_refreshed_when_a_callee_in_another_file_changes(tmp_path: pathlib.Path) -> None:
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    callee = "from hybridpgo._numba import kernel\n\n\n@kernel\ndef g(x):\n    return x + {}\n"
    (pkg / "b.py").write_text(callee.format("1.0"))
    (pkg / "a.py").write_text("from hybridpgo._numba import kernel\nfrom .b import g\n\n\n"
                              "@kernel\ndef f(x):\n    return 2.0 * g(x)\n")
    value, compiled = _run(pkg)
    assert (value, compiled > 0) == (4.0, True)
    value, compiled = _run(pkg)  # unchanged: both kernels come from the cache
    assert (value, compiled) == (4.0, 0)
    (pkg / "b.py").write_text(callee.format("10.0"))  # only the callee's file changes
    value, compiled = _run(pkg)
    assert value == 22.0  # Numba's per-file stamp alone would load f with the old g inlined: 4.0
    assert compiled > 0


def test_package_kernels_carry_the_package_stamp() -> None:
    from hybridpgo._numba import _install_cache_stamp, read_cycles

    assert _install_cache_stamp()  # Numba's private cache API is as expected
    locator = read_cycles._cache._impl._locator
    assert getattr(locator, "_hybridpgo", False)
    assert isinstance(locator.get_source_stamp(), tuple)


def test_constants_passed_between_kernels_do_not_multiply_specializations() -> None:
    """``g(x, True)`` and ``g(x, False)`` from another kernel share one compiled version."""
    import numba

    from hybridpgo._numba import _widen_literals

    def g(x: float, flag: bool, k: int) -> float:
        return x * k if flag else -x

    g_kernel = _widen_literals(numba.njit(cache=False)(g))

    def f(x: float) -> float:
        n = 0
        total = 0.0
        for _ in range(2):
            total += g_kernel(x, True, 3) + g_kernel(x, False, n)
            n += 1
        return total

    assert numba.njit(cache=False)(f)(1.0) == 2 * (3.0 - 1.0)
    assert len(g_kernel.signatures) == 1
    [sig] = g_kernel.signatures
    assert [str(t) for t in sig] == ["float64", "bool", "int64"]


CLOSURE_KEYS = """
import hashlib, importlib, json, pkgutil
from numba.core.registry import CPUDispatcher
from numba.core.serialize import dumps
import hybridpgo

kernels = {}
for info in pkgutil.walk_packages(hybridpgo.__path__, "hybridpgo."):
    if info.name.endswith("__main__"):
        continue
    try:
        module = importlib.import_module(info.name)
    except ImportError:  # an optional extra
        continue
    for attr, value in vars(module).items():
        found = value.items() if isinstance(value, dict) else [(None, value)]
        for key, disp in found:
            if isinstance(disp, CPUDispatcher) and disp.py_func.__closure__:
                kernels[f"{info.name}.{attr}[{key}]"] = disp
out = {}
for name, disp in kernels.items():
    cells = tuple(c.cell_contents for c in disp.py_func.__closure__)
    out[name] = hashlib.sha256(dumps(cells)).hexdigest()
print(json.dumps(out))
"""


def test_closure_kernels_have_the_same_cache_key_in_every_process() -> None:
    """Numba keys a closure's cache entry on the pickle of its cells: a cell holding another
    kernel pickles differently in every process, so the kernel missed the cache and compiled
    again in every run (the plain sweep: seconds per ``hybridpgo optimize``)."""
    import json

    env = dict(os.environ, PYTHONPATH=str(SRC))
    runs = [json.loads(subprocess.run([sys.executable, "-c", CLOSURE_KEYS], env=env,
                                      check=True, capture_output=True, text=True).stdout)
            for _ in range(2)]
    assert any("_sweep.LOOPS" in name for name in runs[0])
    assert runs[0] == runs[1]
