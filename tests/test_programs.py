"""Programs kept across processes (edgevo_jax.programs): the same outputs as jit bit for bit,
loaded without tracing, one program per signature, and plain jit where nothing can be kept."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import programs


class Pair(NamedTuple):
    a: jnp.ndarray
    b: jnp.ndarray


def _fn(pair: Pair, x, scale, *, power: int):
    """A pytree in and out, a static option and a dynamic keyword."""
    y = jnp.tanh(pair.a @ pair.b) * scale + x.sum()
    return {"y": y ** power, "n": Pair(y.sum(), jnp.int32(power))}


def _inputs(seed: int = 0):
    rng = np.random.default_rng(seed)
    return (Pair(rng.normal(size=(5, 4)).astype(np.float32),
                 rng.normal(size=(4, 3)).astype(np.float32)),
            rng.normal(size=7).astype(np.float32))


def _same(out, ref) -> bool:
    return jax.tree.structure(out) == jax.tree.structure(ref) and all(
        np.array_equal(np.asarray(o), np.asarray(r)) for o, r in
        zip(jax.tree.leaves(out), jax.tree.leaves(ref), strict=True))


def test_kept_equals_jit_and_loads_without_tracing(kept_programs, monkeypatch):
    pair, x = _inputs()
    exports = []
    export = programs._Kept._export
    monkeypatch.setattr(programs._Kept, "_export",
                        lambda self, *a: exports.append(a[0].name) or export(self, *a))
    ref = jax.jit(_fn, static_argnames="power")(pair, x, scale=0.5, power=3)
    first = programs.program(_fn, static_argnames="power")
    assert _same(first(pair, x, scale=0.5, power=3), ref)
    stored = list(kept_programs.glob("exported/_fn-*.bin"))
    assert len(stored) == 1 and len(exports) == 1
    again = programs.program(_fn, static_argnames="power")  # as in a new process
    out = again(pair, x, scale=0.5, power=3)
    assert _same(out, ref) and len(exports) == 1  # loaded, not exported
    # float64 numpy and float32 device inputs share the program (jit's dtypes, on device)
    out64 = again(Pair(pair.a.astype(np.float64), jnp.asarray(pair.b)), x, scale=0.5, power=3)
    assert _same(out64, ref) and len(exports) == 1
    # another static value or shape: another program
    again(pair, x, scale=0.5, power=2)
    again(pair, x[:3], scale=0.5, power=3)
    assert len(exports) == 3 and len(list(kept_programs.glob("exported/_fn-*.bin"))) == 3


def test_a_corrupt_or_stale_file_is_exported_again(kept_programs):
    pair, x = _inputs(1)
    ref = jax.jit(_fn, static_argnames="power")(pair, x, scale=2.0, power=1)
    programs.program(_fn, static_argnames="power")(pair, x, scale=2.0, power=1)
    (path,) = kept_programs.glob("exported/_fn-*.bin")
    path.write_bytes(b"not a program")
    assert _same(programs.program(_fn, static_argnames="power")(pair, x, scale=2.0, power=1),
                 ref)
    assert path.read_bytes() != b"not a program"


def test_transformations_and_no_folder_use_jit(tmp_path, kept_programs):
    pair, x = _inputs(2)
    kept = programs.program(_fn, static_argnames="power")

    def loss(a, fn):
        return fn(Pair(a, pair.b), x, 1.0, power=2)["n"].a

    g = jax.grad(loss)(pair.a, kept)
    assert np.array_equal(g, jax.grad(loss)(pair.a, jax.jit(_fn, static_argnames="power")))
    assert not list(kept_programs.glob("exported/*.bin"))  # traced: nothing exported
    programs.keep_programs(None)
    kept(pair, x, 1.0, power=2)
    assert not list(kept_programs.glob("exported/*.bin"))


def test_the_key_holds_the_source(kept_programs, monkeypatch):
    """A stored program is for this package's source only: changed source, new export."""
    pair, x = _inputs(3)
    programs.program(_fn, static_argnames="power")(pair, x, 1.0, power=1)
    monkeypatch.setitem(programs._state, "source", "another source")
    programs.program(_fn, static_argnames="power")(pair, x, 1.0, power=1)
    assert len(list(kept_programs.glob("exported/_fn-*.bin"))) == 2


@pytest.mark.parametrize("static", ["power", ("power",)])
def test_static_argnames_as_str_or_sequence(static):
    pair, x = _inputs(4)
    out = programs.program(_fn, static_argnames=static)(pair, x, 1.0, power=2)
    assert _same(out, jax.jit(_fn, static_argnames="power")(pair, x, 1.0, power=2))


def test_release_compiled_drops_programs_past_the_share_of_memory_maps():
    """Past the share of vm.max_map_count the compiled programs go (and compile again when
    called: a new trace); under it nothing happens."""
    if not Path("/proc/self/maps").is_file():
        pytest.skip("no /proc: memory maps are not counted here")
    traces = []

    @jax.jit
    def f(x):
        traces.append(1)
        return x + 1

    f(np.float32(1))
    assert not programs.release_compiled(share=1.0) and len(traces) == 1
    f(np.float32(2))
    assert len(traces) == 1  # still compiled
    assert programs.release_compiled(share=0.0)  # every process holds some maps
    f(np.float32(3))
    assert len(traces) == 2
