"""docs/config.md: every Config field documented (unit, meaning) and the file current."""

from __future__ import annotations

import ast
import dataclasses

import pytest
from conftest import load_script

from edgevo_jax.config import Config

docs_script = load_script("config_docs")


def test_every_field_has_an_entry_and_the_table_is_current():
    docs = docs_script.field_docs(docs_script.CONFIG_PY.read_text())
    assert [d.name for d in docs] == [f.name for f in dataclasses.fields(Config)]
    for d in docs:
        assert d.group and d.unit and d.meaning, d
        # the default the table shows is the field's default
        assert ast.literal_eval(d.default) == getattr(Config(), d.name), d
    assert docs_script.OUT.read_text() == docs_script.current(), (
        "docs/config.md is stale: run python scripts/config_docs.py")


def test_a_field_without_an_entry_is_named():
    src = '''
class Config:
    # --- a group ---
    a: int = 1
    """[px] documented."""
    b: float = 2.0
    c: int = 3
    """[-] documented."""
'''
    with pytest.raises(ValueError, match="Config.b has no docstring"):
        docs_script.field_docs(src)
    with pytest.raises(ValueError, match="Config.a: its docstring must start with"):
        docs_script.field_docs(src.replace("[px] documented", "documented"))
    docs = docs_script.field_docs(src.replace("    b: float = 2.0\n", ""))
    assert [(d.group, d.name, d.default, d.unit) for d in docs] == [
        ("a group", "a", "1", "px"), ("a group", "c", "3", "-")]
