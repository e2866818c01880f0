"""Place recognition by randomised ferns (``map.recognition``): codes are deterministic, an
image is most like itself and like a view a few pixels away more than like another scene, and
bad input is refused by name."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgevo_jax.datasets import BUNDLED_CLIP, load_sequence
from edgevo_jax.map import encode, make_ferns, similarity
from edgevo_jax.map.recognition import NUM_FERNS, TESTS, thumbnail


@pytest.fixture(scope="module")
def images():
    seq = load_sequence(BUNDLED_CLIP)
    out = []
    for i in (0, 8):
        rgb, depth = seq.rectify_frame(*seq.decode_frame(i))
        out.append((cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), depth))
    return out


def test_the_ferns_are_fixed_and_their_codes_deterministic(images):
    a, b = make_ferns(), make_ferns()
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    gray, depth = images[0]
    code = encode(a, gray, depth)
    assert code.shape == (NUM_FERNS,) and code.dtype == np.uint8
    assert code.max() < 2**TESTS and np.array_equal(code, encode(b, gray, depth))
    assert not np.array_equal(make_ferns(seed=1).row, a.row)


def test_an_image_is_most_like_itself_then_like_a_shifted_view(images):
    ferns = make_ferns()
    gray, depth = images[0]
    shifted = np.roll(gray, 6, axis=1), np.roll(depth, 6, axis=1)
    flipped = gray[::-1, ::-1].copy(), depth[::-1, ::-1].copy()  # the same texture, elsewhere
    codes = np.stack([encode(ferns, *x) for x in ((gray, depth), shifted, flipped)])
    score = similarity(codes, encode(ferns, gray, depth))
    assert score[0] == 1.0
    assert score[1] > score[2] + 0.2, score


def test_a_missing_depth_is_not_read_as_near(images):
    gray, depth = images[0]
    holes = depth.copy()
    holes[:, : holes.shape[1] // 2] = np.nan
    thumb = thumbnail(gray, holes)
    assert np.all(np.isfinite(thumb))
    assert np.all(thumb[1, :, :38] == 0.0)  # no depth: 0, so no depth test passes there
    # far from the hole the measured depths are averaged as before (a hole is no 0 m)
    full = thumbnail(gray, depth)[1, :, 50:]
    seen = thumb[1, :, 50:]
    ok = full > 0
    assert ok.mean() > 0.5
    np.testing.assert_allclose(seen[ok], full[ok], rtol=0.02)


def test_bad_input_is_refused_by_name(images):
    gray, depth = images[0]
    ferns = make_ferns()
    with pytest.raises(ValueError, match="gray must be uint8"):
        encode(ferns, gray.astype(np.float32), depth)
    with pytest.raises(ValueError, match="differ in size"):
        encode(ferns, gray, depth[:-1])
    with pytest.raises(ValueError, match="do not match"):
        similarity(np.zeros((3, 10), np.uint8), np.zeros(11, np.uint8))
    with pytest.raises(ValueError, match="tests <= 8"):
        make_ferns(tests=9)
