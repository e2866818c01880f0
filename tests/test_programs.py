"""Programs kept across processes (edgevo_jax.programs): the same outputs as jit bit for bit,
loaded without tracing, one program per signature, and plain jit where nothing can be kept."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import programs

X86 = platform.machine().lower() in ("x86_64", "amd64")


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


_SETTINGS = (
    "import os, sys, jax\n"
    "from edgevo_jax import Config, Intrinsics, Odometry\n"
    "Odometry(Config(), Intrinsics(525.0, 525.0, 319.5, 239.5))\n"
    "print(jax.config.jax_compilation_cache_dir, "
    "jax.config.jax_persistent_cache_min_compile_time_secs, "
    "'--xla_cpu_max_isa=AVX' in os.environ.get('XLA_FLAGS', '').split())\n"
)


def _settings_in_a_new_process(code: str, **env: str) -> list[str]:
    # this checkout's package, whatever the current folder
    base = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(Path(programs.__file__).parents[1]),
            **env}
    return subprocess.run([sys.executable, "-c", code], env=base, capture_output=True,
                          text=True, check=True).stdout.split()


def test_a_tracker_switches_the_cache_on_with_the_clis_settings(tmp_path):
    """The API's first tracker keeps programs where the CLI does (the default folder under
    HOME), every one of them, with the CLI's batch-exact arithmetic (one cache key for
    both); EDGEVO_CACHE_DIR="" turns the cache off."""
    folder, cap = tmp_path / ".cache" / "edgevo_jax", str(X86)
    out = _settings_in_a_new_process(_SETTINGS, HOME=str(tmp_path))
    assert out == [str(folder), "0.0", cap]
    out = _settings_in_a_new_process(_SETTINGS, HOME=str(tmp_path), EDGEVO_CACHE_DIR="")
    assert out == ["None", "1.0", cap]


def test_a_compilation_cache_the_user_set_stands(tmp_path):
    """A jax_compilation_cache_dir set by the user (here through JAX's environment
    variable) is kept, with its threshold; edgevo's exported programs go to its own folder."""
    code = _SETTINGS + "from edgevo_jax import programs\nprint(programs._state['folder'])\n"
    out = _settings_in_a_new_process(code, HOME=str(tmp_path),
                                     EDGEVO_CACHE_DIR=str(tmp_path / "mine"),
                                     JAX_COMPILATION_CACHE_DIR=str(tmp_path / "user"))
    assert out == [str(tmp_path / "user"), "1.0", str(X86), str(tmp_path / "mine")]


def test_enable_cache_follows_edgevo_cache_dir_in_a_process(tmp_path, monkeypatch):
    """Called again with another EDGEVO_CACHE_DIR, the cache moves (or goes off) with it;
    JAX's folder was not the user's, so it follows."""
    # the session's folder (tests/conftest.py), set by edgevo: not the user's
    assert jax.config.jax_compilation_cache_dir == programs._state["jax_dir"]
    try:
        monkeypatch.setenv("EDGEVO_CACHE_DIR", str(tmp_path / "a"))
        assert programs.enable_cache() == tmp_path / "a"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "a")
        monkeypatch.setenv("EDGEVO_CACHE_DIR", str(tmp_path / "b"))
        assert programs.enable_cache() == tmp_path / "b"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "b")
        monkeypatch.setenv("EDGEVO_CACHE_DIR", "")
        assert programs.enable_cache() is None
        assert jax.config.jax_compilation_cache_dir is None
        assert programs._state["folder"] is None
    finally:  # the session's folder again
        monkeypatch.undo()
        programs.enable_cache()


def test_cache_folder_default_and_xdg(tmp_path, monkeypatch):
    monkeypatch.delenv("EDGEVO_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert programs.cache_folder() == tmp_path / "edgevo_jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert programs.cache_folder() == Path.home() / ".cache" / "edgevo_jax"
    monkeypatch.setenv("EDGEVO_CACHE_DIR", "~/elsewhere")
    assert programs.cache_folder() == Path.home() / "elsewhere"


def test_compile_recorder_records_each_compiled_program():
    """programs.CompileRecorder (scripts/compile_report.py's): one row per XLA compilation,
    named as the compilation cache names its file, with its tracing, lowering and compile
    times."""
    recorder = programs.CompileRecorder(None)

    def squares_plus_one(x):
        return x * x + 1.0

    recorder.start()
    try:
        jax.jit(squares_plus_one)(np.arange(3.0, dtype=np.float32))
    finally:
        recorder.stop()
    rows = [r for r in recorder.rows if r["program"] == "jit_squares_plus_one"]
    assert len(rows) == 1 and not rows[0]["cached"]
    assert rows[0]["compile_s"] > 0 and rows[0]["trace_s"] > 0 and rows[0]["lower_s"] > 0
    jax.jit(squares_plus_one)(np.arange(4.0, dtype=np.float32))  # after stop: not recorded
    assert len([r for r in recorder.rows if r["program"] == "jit_squares_plus_one"]) == 1
