"""edgevo_jax.reports: number formatting, markdown tables, JSON and text result files, integer
lists on the command line."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from edgevo_jax.reports import digest, fmt, int_list, markdown_table, write_json, write_text


def test_fmt():
    assert fmt(0.12345, ".3f") == "0.123" and fmt(7, "d") == "7"
    for missing in (None, math.nan, math.inf, np.float64("nan"), -np.inf):
        assert fmt(missing, ".1f") == "n/a"
        assert fmt(missing, ".1f", missing="-") == "-"


def test_markdown_table():
    text = markdown_table(("a", "bb", "c"), [["1", "2", "3"], ["x", "", "z"]], align="lrr")
    assert text.splitlines() == ["| a | bb | c |", "|---|---:|---:|", "| 1 | 2 | 3 |",
                                 "| x |  | z |"]
    assert markdown_table(("a", "b"), []) == "| a | b |\n|---|---|"
    with pytest.raises(ValueError, match="2 columns"):
        markdown_table(("a", "b"), [["1", "2", "3"]])
    with pytest.raises(ValueError, match="2 columns"):
        markdown_table(("a", "b"), [], align="l")


def test_write_json_and_text(tmp_path):
    path = write_json(tmp_path / "new" / "r.json",
                      {"x": math.nan, "a": np.arange(3), "s": np.float32(0.5), 1: [np.inf]})
    text = path.read_text()
    assert text.endswith("}\n") and "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"x": None, "a": [0, 1, 2], "s": 0.5, "1": [None]}
    assert write_json(tmp_path / "c.json", [1], indent=None).read_text() == "[1]\n"
    assert write_text(tmp_path / "deep" / "er" / "t.md", "# hi\n").read_text() == "# hi\n"


def test_int_list():
    assert int_list("0-4") == [0, 1, 2, 3, 4]
    assert int_list("0,1,2") == [0, 1, 2] and int_list("1,2,3,5") == [1, 2, 3, 5]
    assert int_list("0-2,1,5") == [0, 1, 2, 5]  # duplicates dropped, order kept
    assert int_list(" 3 , 1 - 2 ,") == [3, 1, 2]
    assert int_list("-1") == [-1] and int_list("-3--1") == [-3, -2, -1]
    for bad in ("", ",", "a", "3-1", "1-x", "1.5", "1-2-3"):
        with pytest.raises(ValueError):
            int_list(bad)


def test_digest_tells_a_pose_or_a_verdict_apart_to_the_bit():
    frames = [SimpleNamespace(state="OK", reason=None, keyframe=None)] * 2
    poses = np.stack([np.eye(4)] * 2)
    run = SimpleNamespace(poses=poses, results=frames)
    assert digest(run) == digest(SimpleNamespace(poses=poses.copy(), results=list(frames)))
    nudged = poses.copy()
    nudged[1, 0, 3] = np.nextafter(0.0, 1.0)  # one float64 step
    assert digest(run, nudged) != digest(run)
    weak = [frames[0], SimpleNamespace(state="WEAK", reason="why", keyframe=None)]
    assert digest(SimpleNamespace(poses=poses, results=weak)) != digest(run)
