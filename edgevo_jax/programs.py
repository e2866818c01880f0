"""Jitted programs kept across processes, and the on-disk cache they are kept in.

``program(fn, static_argnames=...)`` is ``jax.jit(fn)`` called at full matmul precision
(``determinism.full_precision``). Once ``keep_programs(folder)`` has been called
(``enable_cache`` does it), each program is exported with ``jax.export`` the first time it
meets a new input signature (the pytree structure, shapes, dtypes and static options of its
inputs) and stored in ``folder``; a later process loads the stored program instead of
tracing and lowering ``fn`` again in Python, which is most of a warm start. XLA's own
compilation cache then supplies the compiled executable. A stored program is found by a
digest of the signature, the package's source, the JAX version, the backend and the matmul
precision: any change to one of them exports again.

``enable_cache()`` switches both on, in one folder, for the CLI and the API alike (the
tracker, ``run`` and ``evaluate`` call it): ``EDGEVO_CACHE_DIR``, by default
``$XDG_CACHE_HOME/edgevo_jax`` or ``~/.cache/edgevo_jax``; ``EDGEVO_CACHE_DIR=""`` turns it
off. It also calls ``determinism.enable_batch_exact``, so that every caller compiles the same
arithmetic under the same cache keys (XLA_FLAGS is part of XLA's key).

Contract: the outputs equal those of ``jax.jit(fn)`` bit for bit (the exported module is the
one jit lowers). Calls under a JAX transformation (tracers among the inputs) and programs
that cannot be exported or stored go through ``jax.jit(fn)`` unchanged. Stored files hold a
pickled pytree structure: the folder is trusted like the compilation cache beside it.

``release_compiled`` drops JAX's compiled programs before a process runs out of memory maps
(each tracker and batch calls it when it starts).
"""
from __future__ import annotations

import functools
import gc
import hashlib
import logging
import os
import pickle
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .determinism import enable_batch_exact, full_precision

_log = logging.getLogger(__name__)
# folder: where programs are kept (None: not kept); jax_dir: the compilation cache folder
# enable_cache set (None: it set none, so a folder set in jax.config is the user's)
_state: dict[str, Any] = {"folder": None, "source": None, "jax_dir": None}
_lock = threading.Lock()


def keep_programs(folder: str | Path | None) -> None:
    """Store exported programs in ``folder`` and load them from there (None: stop)."""
    _state["folder"] = None if folder is None else Path(folder)


#: the environment variable naming the cache folder ("" turns the cache off)
CACHE_ENV = "EDGEVO_CACHE_DIR"
MIN_TIME_ENV = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"


def cache_folder() -> Path | None:
    """The program cache's folder: ``EDGEVO_CACHE_DIR`` when set (None when it is empty:
    no cache), else ``$XDG_CACHE_HOME/edgevo_jax``, else ``~/.cache/edgevo_jax``."""
    path = os.environ.get(CACHE_ENV)
    if path is not None:
        return Path(path).expanduser() if path else None
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "edgevo_jax"


def enable_cache() -> Path | None:
    """Keep edgevo's programs on disk between processes (module doc): exported programs in
    ``cache_folder()``/exported, and XLA's compiled executables in ``cache_folder()`` through
    JAX's persistent compilation cache, every program kept, the small ones too (loading
    beats compiling them again). Settings the user made stand: a
    ``jax_compilation_cache_dir`` already set is used as it is (with its own thresholds), and
    ``enable_batch_exact`` leaves an ISA named in XLA_FLAGS, or ``EDGEVO_EXACT=0``, alone.
    Idempotent; cheap after the first call. Returns the folder, or None when the cache is
    off (``EDGEVO_CACHE_DIR=""``: nothing is changed then but the batch-exact arithmetic)."""
    enable_batch_exact()
    folder = cache_folder()
    keep_programs(folder)
    current, ours = jax.config.jax_compilation_cache_dir, _state["jax_dir"]
    if current is None or current == ours:  # not the user's: follow EDGEVO_CACHE_DIR
        wanted = None if folder is None else str(folder)
        if wanted != current:
            from jax.experimental.compilation_cache import compilation_cache

            jax.config.update("jax_compilation_cache_dir", wanted)
            if wanted is not None and MIN_TIME_ENV not in os.environ:
                jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            # JAX decides at its first compilation whether it caches; a process that
            # compiled before (without a folder) decides again at its next one
            compilation_cache.reset_cache()
        _state["jax_dir"] = wanted
    return folder


def program(fn: Callable, *, static_argnames: str | Sequence[str] = ()) -> Callable:
    """``fn`` jitted with ``static_argnames``, at full precision, kept across processes
    (module doc). Static options are passed by keyword; other keywords are inputs."""
    names = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
    return full_precision(_Kept(jax.jit(fn, static_argnames=names),
                                getattr(fn, "__name__", "program"), frozenset(names)))


def _source_digest() -> str:
    """Digest of the package's Python source (a stored program is valid for this code only)."""
    with _lock:
        if _state["source"] is None:
            h = hashlib.sha256()
            root = Path(__file__).parent
            for path in sorted(root.rglob("*.py")):
                h.update(str(path.relative_to(root)).encode())
                h.update(path.read_bytes())
            _state["source"] = h.hexdigest()
    return _state["source"]


def _spec(x: Any) -> tuple:
    """(shape, dtype, weak type) of one input leaf, as jit sees it (float64 is float32
    unless x64 is on)."""
    if isinstance(x, np.ndarray):
        return x.shape, _dtype_name(x.dtype, jax.config.jax_enable_x64), False
    if isinstance(x, jax.Array):
        return x.shape, _dtype_name(x.dtype, jax.config.jax_enable_x64), bool(x.weak_type)
    a = jax.typeof(x)
    return a.shape, str(a.dtype), a.weak_type


@functools.cache
def _dtype_name(dtype: np.dtype, x64: bool) -> str:
    """The name of ``dtype`` as jit canonicalises it with x64 on or off (memoised: every
    call of a kept program names the dtypes of all its inputs)."""
    return str(jax.dtypes.canonicalize_dtype(dtype))


def _jit_call(exported: jax.export.Exported, name: str) -> Callable:
    """The exported program, jitted with every input on the default device: numpy inputs
    and device arrays (committed or not) share one compiled program. Its XLA module is
    named after the program (``jit_<name>``: logs and the compilation cache tell them apart)."""
    def call(*args):
        return exported.call(*args)

    call.__name__ = call.__qualname__ = name
    return jax.jit(call, in_shardings=jax.sharding.SingleDeviceSharding(
        jax.local_devices()[0]))


class _Kept:
    """A jitted function with its exported programs, one per input signature."""

    def __init__(self, jitted: Callable, name: str, static_names: frozenset[str]):
        self.jitted, self.name, self.static_names = jitted, name, static_names
        self._loaded: dict[tuple, tuple[Callable, Any] | None] = {}  # None: use ``jitted``

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        folder = _state["folder"]
        static = {k: v for k, v in kwargs.items() if k in self.static_names}
        leaves, tree = jax.tree.flatten((args, {k: v for k, v in kwargs.items()
                                               if k not in self.static_names}))
        if folder is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self.jitted(*args, **kwargs)
        sig = (tree, tuple(sorted(static.items())), tuple(_spec(x) for x in leaves),
               jax.config.jax_default_matmul_precision, jax.config.jax_enable_x64)
        kept = self._loaded.get(sig, False)
        if kept is False:
            kept = self._loaded[sig] = self._load_or_export(folder, sig, leaves, tree, static)
        if kept is None:
            return self.jitted(*args, **kwargs)
        call, out_tree = kept
        return jax.tree.unflatten(out_tree, call(*leaves))

    def _load_or_export(self, folder: Path, sig: tuple, leaves: list, tree: Any,
                        static: dict) -> tuple[Callable, Any] | None:
        device = jax.local_devices()[0]
        key = hashlib.sha256(repr((sig, self.name, _source_digest(), jax.__version__,
                                   device.platform, device.device_kind)).encode()).hexdigest()
        path = folder / "exported" / f"{self.name}-{key[:32]}.bin"
        try:
            serialized, out_tree = pickle.loads(path.read_bytes())
            return _jit_call(jax.export.deserialize(bytearray(serialized)), self.name), out_tree
        except FileNotFoundError:
            pass
        except Exception as err:  # a corrupt or stale file: export again
            _log.debug("stored program %s unreadable (%s): exporting again", path, err)
        try:
            return self._export(path, leaves, tree, static)
        except Exception as err:  # not exportable here: plain jit
            _log.debug("program %s not kept (%s): plain jit", self.name, err)
            return None

    def _export(self, path: Path, leaves: list, tree: Any,
                static: dict) -> tuple[Callable, Any]:
        out_trees: list = []

        def flat(*values):
            args, kwargs = jax.tree.unflatten(tree, values)
            out, out_tree = jax.tree.flatten(self.jitted(*args, **kwargs, **static))
            out_trees.append(out_tree)
            return out

        flat.__name__ = flat.__qualname__ = self.name
        specs = [jax.ShapeDtypeStruct(s, d, weak_type=w) for s, d, w in map(_spec, leaves)]
        exported = jax.export.export(jax.jit(flat))(*specs)
        data = pickle.dumps((bytes(exported.serialize()), out_trees[0]))
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)  # whole files only, whatever runs beside
        return _jit_call(exported, self.name), out_trees[0]


#: share of this process's memory-map limit past which ``release_compiled`` drops programs
MAP_SHARE = 0.75


def release_compiled(*, share: float = MAP_SHARE) -> bool:
    """Drop JAX's compiled programs when this process holds more than ``share`` of its
    memory-map limit. XLA's CPU backend maps every compiled kernel into memory (~2,500
    maps per tracker configuration on this project's machine); past Linux's
    vm.max_map_count (65,530 by default) its next compilation crashes the process. The
    programs compile (or load, when kept) again the next time they run. Returns whether it
    dropped them; False where /proc does not tell (not Linux)."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as f:
            count = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if count <= share * limit:
        return False
    _log.info("%d of %d memory maps in use: dropping JAX's compiled programs", count, limit)
    jax.clear_caches()
    gc.collect()
    return True


# the events JAX records per program (jax._src.dispatch), and its cache's (jax._src.compiler)
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
LOWER_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
CACHE_MISS_EVENT = "/jax/compilation_cache/cache_misses"


class CompileRecorder:
    """Listens to JAX's monitoring events and gathers one record per compiled program in
    ``rows`` (``program``: the module name, ``jit_`` and the function's, as the compilation
    cache names its file; ``trace_s``, ``lower_s``, ``compile_s``; ``cached``: loaded from
    the cache, False compiled, None unknown; ``bytes``: see ``assign_sizes``). A program's
    trace and lowering come before its compilation in the thread that runs it, and a cache
    hit or miss inside it, so they are matched per thread. ``cache_dir``: the compilation
    cache's folder (None: none)."""

    def __init__(self, cache_dir: Path | None):
        self.cache_dir, self.rows = cache_dir, []
        self._local, self._lock = threading.local(), threading.Lock()

    def start(self) -> None:
        """Listen to JAX's events (until ``stop``)."""
        import jax.monitoring

        jax.monitoring.register_event_listener(self.on_event)
        jax.monitoring.register_event_duration_secs_listener(self.on_duration)

    def stop(self) -> None:
        """Stop listening."""
        import jax.monitoring

        jax.monitoring.unregister_event_listener(self.on_event)
        jax.monitoring.unregister_event_duration_listener(self.on_duration)

    def _pending(self) -> dict:
        if not hasattr(self._local, "pending"):
            self._local.pending = {"trace_s": 0.0, "lower_s": 0.0, "cached": None}
        return self._local.pending

    def on_event(self, event: str, **_: Any) -> None:
        """A JAX event: a cache hit or miss marks the program this thread compiles next."""
        if event in (CACHE_HIT_EVENT, CACHE_MISS_EVENT):
            self._pending()["cached"] = event == CACHE_HIT_EVENT

    def on_duration(self, event: str, secs: float, fun_name: str = "?", **_: Any) -> None:
        """A JAX duration: tracing and lowering add to this thread's next program; a
        compilation closes its record."""
        pending = self._pending()
        if event == TRACE_EVENT:
            pending["trace_s"] += secs
        elif event == LOWER_EVENT:
            pending["lower_s"] += secs
        elif event == COMPILE_EVENT:
            name = fun_name.replace("(", "_").rstrip(")")  # jit(f) -> jit_f, as cached
            with self._lock:
                self.rows.append({"program": name, **pending, "compile_s": secs,
                                  "bytes": 0})
            self._local.pending = {"trace_s": 0.0, "lower_s": 0.0, "cached": None}

    def assign_sizes(self) -> None:
        """Give each compiled program the size of its cache entry: the entries of one
        module name in the order they were written, to its compilations in the order they
        finished (0 where none: loaded, or no cache)."""
        if self.cache_dir is None or not self.cache_dir.is_dir():
            return
        for name in {r["program"] for r in self.rows}:
            files = sorted(self.cache_dir.glob(f"{name}-*-cache"),
                           key=lambda p: p.stat().st_mtime_ns)
            compiled = [r for r in self.rows if r["program"] == name and not r["cached"]]
            for row, path in zip(compiled, files, strict=False):
                row["bytes"] = path.stat().st_size
