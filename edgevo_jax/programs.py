"""Jitted programs kept across processes.

``program(fn, static_argnames=...)`` is ``jax.jit(fn)`` called at full matmul precision
(``determinism.full_precision``). Once ``keep_programs(folder)`` has been called (the run
pipeline does it with the compilation cache, ``pipeline.run.enable_compilation_cache``), each
program is exported with ``jax.export`` the first time it meets a new input signature (the
pytree structure, shapes, dtypes and static options of its inputs) and stored in ``folder``;
a later process loads the stored program instead of tracing and lowering ``fn`` again in
Python, which is most of a warm start. XLA's own compilation cache then supplies the compiled
executable. A stored program is found by a digest of the signature, the package's source, the
JAX version, the backend and the matmul precision: any change to one of them exports again.

Contract: the outputs equal those of ``jax.jit(fn)`` bit for bit (the exported module is the
one jit lowers). Calls under a JAX transformation (tracers among the inputs) and programs
that cannot be exported or stored go through ``jax.jit(fn)`` unchanged. Stored files hold a
pickled pytree structure: the folder is trusted like the compilation cache beside it.

``release_compiled`` drops JAX's compiled programs before a process runs out of memory maps
(each tracker and batch calls it when it starts).
"""
from __future__ import annotations

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

from .determinism import full_precision

_log = logging.getLogger(__name__)
_state: dict[str, Any] = {"folder": None, "source": None}
_lock = threading.Lock()


def keep_programs(folder: str | Path | None) -> None:
    """Store exported programs in ``folder`` and load them from there (None: stop)."""
    _state["folder"] = None if folder is None else Path(folder)


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
    if isinstance(x, np.ndarray | jax.Array):
        return (x.shape, str(jax.dtypes.canonicalize_dtype(x.dtype)),
                bool(getattr(x, "weak_type", False)))
    a = jax.typeof(x)
    return a.shape, str(a.dtype), a.weak_type


def _jit_call(exported: jax.export.Exported) -> Callable:
    """The exported program, jitted with every input on the default device: numpy inputs
    and device arrays (committed or not) share one compiled program."""
    return jax.jit(exported.call, in_shardings=jax.sharding.SingleDeviceSharding(
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
            return _jit_call(jax.export.deserialize(bytearray(serialized))), out_tree
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

        specs = [jax.ShapeDtypeStruct(s, d, weak_type=w) for s, d, w in map(_spec, leaves)]
        exported = jax.export.export(jax.jit(flat))(*specs)
        data = pickle.dumps((bytes(exported.serialize()), out_trees[0]))
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)  # whole files only, whatever runs beside
        return _jit_call(exported), out_trees[0]


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
