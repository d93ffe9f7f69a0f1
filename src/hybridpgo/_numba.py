"""The only place Numba options live (docs/contributing.md#kernels).

``kernel`` is the decorator every hot loop uses.  ``fastmath`` stays off: it breaks NaN checks
and bit-reproducibility.

Kernels are optimized at LLVM ``-O1`` (:data:`OPT_LEVEL`) rather than Numba's ``-O3``: measured
on M3500, the sweeps and the exact solver's assembly run as fast, and a first run
compiles about 16% less.  ``NUMBA_OPT``, when set, wins; ``HYBRIDPGO_OPT=3`` restores the default
for the package alone.

Two more things live here because they concern every kernel:

* **Cache freshness.**  Numba's on-disk cache (``cache=True``) keys a kernel on the hash of the
  one file that defines it, but a compiled kernel contains the machine code of every kernel it
  calls.  Editing ``_step.py`` would leave ``_sweep.py``'s cached ``sweep`` running the old
  step.  :func:`_install_cache_stamp` makes the stamp of every hybridpgo kernel also depend on
  the hash of all the package's kernel-side sources (everything but ``cli/``), so any edit there
  recompiles, and a stale cache can never be loaded.
* **Compile watching.**  :func:`compile_status` tells how many kernels this process has
  compiled (cache misses) and which one is compiling now, for the command line's
  "compiling kernels (first run only)" display; :func:`on_first_compile` lets a caller
  announce compilation only when it actually happens.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, NamedTuple, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])

_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


def kernel(fn: F) -> F:
    """Compile ``fn`` with the project's Numba options (typed once here for mypy).

    A call from another kernel compiles ``fn`` for its arguments' types with literal constants
    widened (``relax(..., False)`` and ``relax(..., True)`` share one ``boolean`` version):
    Numba would otherwise compile one version per constant, and type inference even compiles
    throw-away versions for the constant a variable starts with (``nbuf = 0``), each with its
    whole call tree.  LLVM still sees the constant after inlining, so the runtime is the same.
    """
    dispatcher = numba.njit(**_OPTIONS)(fn)
    return _watched(_at_opt_level(_widen_literals(_checked_cache(dispatcher))))  # type: ignore[no-any-return]


#: LLVM optimization level of the package's kernels (Numba's default is 3; module docstring).
OPT_LEVEL = {"0": 0, "2": 2, "3": 3}.get(os.environ.get("HYBRIDPGO_OPT", ""), 1)


def _effective_opt_level() -> str:
    """The level kernels are compiled at (part of the cache stamp: switching recompiles)."""
    return os.environ.get("NUMBA_OPT") or str(OPT_LEVEL)


def _at_opt_level(dispatcher: Any) -> Any:
    """Compile ``dispatcher`` (and what it compiles in turn) at LLVM ``-O{OPT_LEVEL}``, unless
    the user set ``NUMBA_OPT``.  Numba reads ``config.OPT`` when it builds each pass manager, so
    setting it around the compilation is enough (the machine-code generator keeps its own)."""
    compile_sig = dispatcher.compile

    def compile(sig: Any) -> Any:
        from numba.core import config

        saved = getattr(config, "OPT", None)
        if saved is None or "NUMBA_OPT" in os.environ or int(saved) == OPT_LEVEL:
            return compile_sig(sig)
        setattr(config, "OPT", type(saved)(OPT_LEVEL))  # noqa: B010 (Numba's _OptLevel, an int)
        try:
            return compile_sig(sig)
        finally:
            setattr(config, "OPT", saved)  # noqa: B010

    dispatcher.compile = compile
    return dispatcher


def _widen_literals(dispatcher: Any) -> Any:
    from numba.core import types

    typed = dispatcher.get_call_template

    def get_call_template(args: Any, kws: Any) -> Any:
        return typed(tuple(types.unliteral(a) for a in args),
                     {k: types.unliteral(v) for k, v in kws.items()})

    dispatcher.get_call_template = get_call_template
    return dispatcher


# --------------------------------------------------------------------------- parallel compile
class CompileHooks:
    """Called around every package kernel's compilation (or cache load) by its dispatcher;
    set by :mod:`hybridpgo._precompile` (None: nothing to do).

    ``before(name)`` runs before Numba looks at its cache for a kernel with no compiled version
    in this process (the first process waits there while its helper compiles ``name``);
    ``after(name)`` runs once the kernel is compiled *and saved* to the cache (the helper
    reports it).  ``name`` is ``module.qualname``.
    """

    before: Callable[[str], None] | None = None
    after: Callable[[str], None] | None = None


def kernel_name(dispatcher: Any) -> str:
    """``module.qualname`` of a kernel, as the compile hooks name it."""
    fn = dispatcher.py_func
    return f"{fn.__module__}.{fn.__qualname__}"


def _watched(dispatcher: Any) -> Any:
    compile_sig = dispatcher.compile
    name = kernel_name(dispatcher)

    def compile(sig: Any) -> Any:
        before, after = CompileHooks.before, CompileHooks.after
        if before is not None and not dispatcher.overloads:
            before(name)
        entry = compile_sig(sig)  # Numba's compile: cache load, or compile then save
        if after is not None:
            after(name)
        return entry

    dispatcher.compile = compile
    return dispatcher


def _checked_cache(dispatcher: Any) -> Any:
    """Load a cache entry only if it was compiled for the signature asked for.

    Numba numbers a kernel's data files in its index (``f.1.nbc``, ``f.2.nbc``); two processes
    saving *different* signatures of one kernel at the same time can both pick ``.1`` and leave
    an index entry pointing to the other signature's code.  Such an entry is treated as a miss
    (compiled again) instead of being loaded under the wrong signature.
    """
    cache = getattr(dispatcher, "_cache", None)
    load = getattr(cache, "load_overload", None)
    if load is None:  # pragma: no cover - a Numba without a per-dispatcher cache
        return dispatcher

    def load_overload(sig: Any, target_context: Any) -> Any:
        cres = load(sig, target_context)
        if cres is None:
            return None
        from numba.core import sigutils

        args, _ = sigutils.normalize_signature(sig)
        if tuple(getattr(cres.signature, "args", ())) != tuple(args):
            return None
        return cres

    setattr(cache, "load_overload", load_overload)  # noqa: B010 (cache: Any | None for mypy)
    return dispatcher


def is_cached(dispatcher: Any) -> bool:
    """Whether Numba's cache holds a version of this kernel for the current sources (its index
    exists and carries the current stamp); True when that cannot be told (Numba's private cache
    API changed), so a caller that would do extra work for a cold cache does nothing."""
    try:
        return bool(dispatcher._cache._cache_file._load_index())
    except Exception:  # private API: assume warm
        return True


# --------------------------------------------------------------------------- cache freshness
#: Source trees whose kernels get the package-wide stamp (tests may add one).
STAMP_ROOTS: list[pathlib.Path] = [pathlib.Path(__file__).resolve().parent]
#: Sub-directories of a root that no kernel depends on (the command line).
_UNSTAMPED_DIRS = ("cli",)


def _tree_files(root: pathlib.Path) -> list[pathlib.Path]:
    return sorted(p for p in root.rglob("*.py")
                  if not (set(p.relative_to(root).parts[:-1]) & set(_UNSTAMPED_DIRS)))


def _tree_stamp(root: pathlib.Path) -> str:
    """SHA-256 over the names and contents of the kernel-side sources under ``root``.

    Memoized on every file's (mtime, size), like Numba's own per-file stamp, so a process that
    edits a file and recompiles sees the change.
    """
    files = _tree_files(root)
    key = tuple((str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in files)
    return _hash_files(key)


@functools.lru_cache(maxsize=8)
def _hash_files(key: tuple[tuple[str, int, int], ...]) -> str:
    h = hashlib.sha256()
    for name, _, _ in key:
        h.update(name.encode())
        h.update(pathlib.Path(name).read_bytes())
    return h.hexdigest()


def _stamp_root(py_file: str) -> pathlib.Path | None:
    try:
        path = pathlib.Path(py_file).resolve()
    except OSError:
        return None
    for root in STAMP_ROOTS:
        if path.is_relative_to(root):
            rel = path.relative_to(root).parts[:-1]
            return None if set(rel) & set(_UNSTAMPED_DIRS) else root
    return None


def _install_cache_stamp() -> bool:
    """Put a locator in front of Numba's that adds the package stamp; False if Numba's private
    cache API is not as expected (then Numba's per-file stamp is used unchanged)."""
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover - a Numba without the module
        return False
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    classes = getattr(impl, "_locator_classes", None)
    base = getattr(caching, "_CacheLocator", None)
    if not isinstance(classes, list) or base is None:  # pragma: no cover
        return False
    locators: list[Any] = classes
    if any(getattr(c, "_hybridpgo", False) for c in locators):
        return True

    class PackageStampLocator(base):  # type: ignore[misc, valid-type]
        """Numba's locator for the file, with the package stamp added to the source stamp."""

        _hybridpgo = True

        def __init__(self, inner: Any, root: pathlib.Path) -> None:
            self._inner = inner
            self._root = root

        def ensure_cache_path(self) -> None:
            self._inner.ensure_cache_path()

        def get_cache_path(self) -> Any:
            return self._inner.get_cache_path()

        def get_source_stamp(self) -> Any:
            return (self._inner.get_source_stamp(), _tree_stamp(self._root),
                    _effective_opt_level())

        def get_disambiguator(self) -> Any:
            return self._inner.get_disambiguator()

        @classmethod
        def from_function(cls, py_func: Any, py_file: str) -> Any:
            root = _stamp_root(py_file)
            if root is None:
                return None
            for other in locators:
                if other is cls:
                    continue
                inner = other.from_function(py_func, py_file)
                if inner is not None:
                    return cls(inner, root)
            return None

    locators.insert(0, PackageStampLocator)
    return True


_install_cache_stamp()


# --------------------------------------------------------------------------- compile watching
class CompileStatus(NamedTuple):
    """What Numba has compiled in this process (cache loads do not count)."""

    compiled: int
    """Kernels (signatures) compiled so far, Numba's own helpers included."""
    current: str | None
    """Name of the kernel compiling now (the innermost one), or None."""
    seconds: float
    """Wall time spent compiling (outermost compilations only)."""


class _Watch:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.compiled = 0
        self.stack: list[str] = []
        self.t_start = 0.0
        self.seconds = 0.0
        self.callbacks: list[Callable[[], None]] = []

    def start(self, name: str) -> None:
        with self.lock:
            if not self.stack:
                self.t_start = time.perf_counter()
            self.stack.append(name)
            callbacks, self.callbacks = self.callbacks, []
        for cb in callbacks:
            cb()

    def end(self) -> None:
        with self.lock:
            if self.stack:
                self.stack.pop()
            self.compiled += 1
            if not self.stack:
                self.seconds += time.perf_counter() - self.t_start


_WATCH = _Watch()


def _install_watch() -> None:
    from numba.core import event

    class Listener(event.Listener):  # type: ignore[misc]
        def on_start(self, ev: Any) -> None:
            disp = (ev.data or {}).get("dispatcher")
            fn = getattr(disp, "py_func", None)
            _WATCH.start(getattr(fn, "__name__", "?"))

        def on_end(self, ev: Any) -> None:
            _WATCH.end()

    event.register("numba:compile", Listener())


_install_watch()


def compile_status() -> CompileStatus:
    """Kernels compiled so far in this process and the one compiling now."""
    with _WATCH.lock:
        current = _WATCH.stack[-1] if _WATCH.stack else None
        seconds = _WATCH.seconds + (time.perf_counter() - _WATCH.t_start if current else 0.0)
        return CompileStatus(_WATCH.compiled, current, seconds)


@contextmanager
def on_first_compile(callback: Callable[[], None]) -> Iterator[None]:
    """Call ``callback`` once when Numba starts compiling inside the ``with`` block (a cache
    load is not a compilation); not at all if everything comes from the cache."""
    with _WATCH.lock:
        _WATCH.callbacks.append(callback)
    try:
        yield
    finally:
        with _WATCH.lock:
            if callback in _WATCH.callbacks:
                _WATCH.callbacks.remove(callback)


# --------------------------------------------------------------------------- cycle counter
def _make_cycle_counter() -> Any:
    """``cycle_counter()`` -> uint64: the CPU's cycle counter (``llvm.readcyclecounter``).

    Used to time single constraint updates inside compiled sweeps without leaving compiled code
    (~20 ns per read).  Counts are converted to seconds by calibrating against
    ``time.perf_counter`` around each sweep.
    """
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    @intrinsic
    def cycle_counter(typingctx: Any) -> Any:
        sig = types.uint64()

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            fnty = ir.FunctionType(ir.IntType(64), [])
            fn = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
                builder.module, fnty, "llvm.readcyclecounter"
            )
            return builder.call(fn, [])

        return sig, codegen

    return cycle_counter


cycle_counter = _make_cycle_counter()


@kernel
def read_cycles() -> int:
    """The cycle counter, read from Python."""
    return cycle_counter()  # type: ignore[no-any-return]


@functools.cache
def cycles_per_second() -> float:
    """Frequency of the cycle counter, calibrated once against ``time.perf_counter``."""
    read_cycles()
    c0, t0 = read_cycles(), time.perf_counter()
    time.sleep(0.05)
    c1, t1 = read_cycles(), time.perf_counter()
    return float(c1 - c0) / (t1 - t0)

