"""The public API's conventions (as dm_pix checks its own): a curated ``edgevo_jax``
namespace, options keyword-only, documented, and an import that pulls in no optional extra."""

from __future__ import annotations

import inspect
import subprocess
import sys

import edgevo_jax

API = ["AlignResult", "Camera", "Config", "FrameResult", "Intrinsics", "Odometry", "Pose",
       "align", "ate", "enable_batch_exact", "evaluate", "load_sequence", "rpe", "run",
       "summarise"]
#: the leading data arguments each API function takes positionally; everything after is an
#: option, keyword-only
POSITIONAL = {"Odometry": ("config", "intrinsics"), "evaluate": ("sequences", "configs"),
              "load_sequence": ("path",), "run": ("seq", "config"), "summarise": ("run", "seq"),
              "enable_batch_exact": (), "ate": ("groundtruth", "estimate"),
              "rpe": ("groundtruth", "estimate"),
              "align": ("source_rgb", "source_depth", "target_rgb", "target_depth")}


def test_the_namespace_is_curated():
    assert sorted(edgevo_jax.__all__) == sorted(API)
    for name in API:
        assert getattr(edgevo_jax, name).__doc__, f"edgevo_jax.{name} has no docstring"


def test_options_are_keyword_only():
    for name, data in POSITIONAL.items():
        obj = getattr(edgevo_jax, name)
        sig = inspect.signature(obj.__init__ if inspect.isclass(obj) else obj)
        params = [p for p in sig.parameters.values() if p.name != "self"]
        positional = [p.name for p in params if p.kind in (
            p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        assert tuple(positional) == data, f"{name}: positional {positional}, expected {data}"
        for p in params:
            if p.name not in data:
                assert p.kind is p.KEYWORD_ONLY, f"{name}({p.name}=...) must be keyword-only"


def test_importing_pulls_in_no_optional_extra():
    code = ("import sys, edgevo_jax; "
            "print(sorted(m for m in ('matplotlib', 'optax', 'open3d', 'rosbags', 'rerun') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split("\n")[-2]
    assert out == "[]"
