"""Nothing lost, nothing random: a run stopped mid-way (Ctrl-C, a bad frame) keeps every pose
it finished in ``<out>.part`` and says where it stopped; two runs with the same inputs and seed
write byte-identical trajectory files."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.config import Config
from edgevo_jax.datasets import TumSequence, load_sequence
from edgevo_jax.io import read_trajectory
from edgevo_jax.runs.run import run_sequence

pytestmark = pytest.mark.slow  # each test tracks real frames

FRAMES = 5


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> bytes:
    """The trajectory file of an uninterrupted run over the first FRAMES frames."""
    out = tmp_path_factory.mktemp("ref") / "traj.txt"
    run = run_sequence(load_sequence(BUNDLED_CLIP), Config(), out=out, progress=False,
                       max_frames=FRAMES)
    assert run.stopped_at is None and len(run.results) == FRAMES
    return out.read_bytes()


def test_same_inputs_and_seed_give_byte_identical_files(reference, tmp_path):
    out = tmp_path / "again.txt"
    run_sequence(load_sequence(BUNDLED_CLIP), Config(seed=0), out=out, progress=False,
                 max_frames=FRAMES)
    assert out.read_bytes() == reference
    assert len(reference.splitlines()) == FRAMES
    assert not Path(f"{out}.part").exists()


@pytest.mark.parametrize("k", [1, 3])
def test_interrupted_run_keeps_its_finished_lines(reference, tmp_path, monkeypatch, k):
    """Ctrl-C while frame k is decoded: the frames finished before it are on disk, the final
    name is never created, and the exception says where the run stopped."""
    decode = TumSequence.decode_frame

    def decode_or_interrupt(self, i):
        if i == k:
            raise KeyboardInterrupt
        return decode(self, i)

    monkeypatch.setattr(TumSequence, "decode_frame", decode_or_interrupt)
    out = tmp_path / "traj.txt"
    with pytest.raises(KeyboardInterrupt) as info:
        run_sequence(load_sequence(BUNDLED_CLIP), Config(), out=out, progress=False,
                     max_frames=FRAMES)
    run = info.value.run_result
    # frame k-1 is decoded and pre-processed, not yet tracked (the runner is one frame ahead)
    assert run.stopped_at == len(run.results) == k - 1
    part = Path(f"{out}.part")
    assert not out.exists() and part.is_file()
    kept = part.read_bytes()
    assert kept == b"".join(reference.splitlines(keepends=True)[: k - 1])
    note = " ".join(getattr(info.value, "__notes__", []))
    assert f"stopped at frame {k - 1} of {FRAMES}" in note, note
    assert f"the {k - 1} poses done are in {part}" in note, note


def test_bad_frame_mid_run_keeps_the_frames_before_it(reference, tmp_path):
    """A depth PNG whose data is damaged (header and end intact, so loading passes) stops the
    run at its frame with its name; the frames before it are kept."""
    root = tmp_path / BUNDLED_CLIP.name
    shutil.copytree(BUNDLED_CLIP, root, copy_function=shutil.copyfile)
    for p in [root, *root.rglob("*")]:
        p.chmod(0o755 if p.is_dir() else 0o644)  # the packaged files may be read-only
    seq = load_sequence(root)
    bad = seq.depth_files[3]
    data = bytearray(bad.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 2000] = bytes(b ^ 0x5A for b in data[mid : mid + 2000])
    bad.write_bytes(bytes(data))
    seq = load_sequence(root)  # the header and the end are whole: loading cannot tell
    out = tmp_path / "traj.txt"
    with pytest.raises(ValueError, match=rf"cannot decode depth image {re.escape(str(bad))}"):
        run_sequence(seq, Config(), out=out, progress=False, max_frames=FRAMES)
    part = Path(f"{out}.part")
    assert not out.exists()
    assert part.read_bytes() == b"".join(reference.splitlines(keepends=True)[:2])
    np.testing.assert_array_equal(read_trajectory(part)[0], seq.timestamps[:2])
