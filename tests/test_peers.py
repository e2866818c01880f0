"""The peers (edgevo_jax.peers): chaining a peer's motions into poses, failures as lost frames
with constant velocity, and a missing library or OpenCV without cv2.Odometry reported as
PeerMissing. A real peer on real frames: tests/test_bench.py."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from edgevo_jax.peers import PeerMissing, camera_matrix, make_peer, track_peer


class _Frames:
    """A source of n blank frames (``decode_frame`` and ``rectify_frame``, as a Source's)."""

    def __init__(self, n: int) -> None:
        self.n, self.rectified = n, 0

    def decode_frame(self, i: int):
        assert 0 <= i < self.n
        return np.zeros((4, 6, 3), np.uint8), np.full((4, 6), 5000, np.uint16)

    def rectify_frame(self, rgb, raw):
        self.rectified += 1
        return rgb, raw.astype(np.float32) / 5000.0


class _Scripted:
    """A peer answering each frame with the next of ``outcomes`` ("raise": an exception)."""

    description = "scripted"

    def __init__(self, outcomes) -> None:
        self.outcomes, self.calls = list(outcomes), 0

    def step(self, rgb, depth):
        assert depth.dtype == np.float32 and depth[0, 0] == 1.0  # metres, rectified
        outcome = self.outcomes[self.calls]
        self.calls += 1
        if isinstance(outcome, str):
            raise RuntimeError("boom")
        return outcome


def _moving_z(dz: float) -> np.ndarray:
    """Rt = T_current_previous of a camera that moves ``dz`` along its +z."""
    rt = np.eye(4)
    rt[:3, 3] = [0.0, 0.0, -dz]
    return rt


def test_failed_pairs_are_lost_frames_with_constant_velocity():
    """Rt is T_current_previous; failures (None, non-finite, exceptions) repeat the last
    motion, are counted and named, and make the frame LOST."""
    step = _moving_z(0.01)
    peer = _Scripted([None, step, None, np.full((4, 4), np.nan), "raise", step])
    first = np.eye(4)
    first[:3, 3] = [1.0, 2.0, 3.0]
    frames = _Frames(6)
    track = track_peer(peer, frames, 6, first)
    assert frames.rectified == 6 and len(track.frame_ms) == len(track.decode_ms) == 6
    assert track.lost == 3 and track.description == "scripted"
    assert track.states == ["OK", "OK", "LOST", "LOST", "LOST", "OK"]
    assert "RuntimeError: boom" in track.failures[-1] and "frame 2" in track.failures[0]
    z = np.array([p[2, 3] for p in track.poses])
    np.testing.assert_allclose(z, 3.0 + 0.01 * np.arange(6))
    np.testing.assert_array_equal(track.poses[0], first)


def test_identity_before_the_first_success_and_a_failing_first_frame():
    """Before any motion a failure keeps the camera where it is; an exception at frame 0 is
    a lost frame (frame 0's None is not)."""
    track = track_peer(_Scripted(["raise", None, _moving_z(0.02), None]), _Frames(4), 4,
                       np.eye(4))
    assert track.lost == 3 and track.states == ["OK", "LOST", "OK", "LOST"]
    np.testing.assert_allclose([p[2, 3] for p in track.poses], [0.0, 0.0, 0.02, 0.04])
    quiet = track_peer(_Scripted([None, _moving_z(0.0)]), _Frames(2), 2, np.eye(4))
    assert quiet.lost == 0 and quiet.failures == []


def test_failure_messages_are_capped():
    track = track_peer(_Scripted([None] * 12), _Frames(12), 12, np.eye(4))
    assert track.lost == 11 and len(track.failures) == 5


def test_camera_matrix():
    np.testing.assert_array_equal(camera_matrix((500, 510, 320, 240)),
                                  [[500, 0, 320], [0, 510, 240], [0, 0, 1]])


def test_unknown_and_missing_peers(monkeypatch):
    with pytest.raises(PeerMissing, match="unknown method 'no_such_peer'"):
        make_peer("no_such_peer", (500.0, 500.0, 320.0, 240.0), 640, 480)
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise
    with pytest.raises(PeerMissing, match="^cannot import open3d"):
        make_peer("o3d_color", (500.0, 500.0, 320.0, 240.0), 640, 480)


def test_opencv_without_odometry_is_reported_missing(monkeypatch):
    cv2 = pytest.importorskip("cv2")
    if hasattr(cv2, "Odometry"):
        monkeypatch.delattr(cv2, "Odometry")
    with pytest.raises(PeerMissing, match="no cv2.Odometry"):
        make_peer("cv2_depth", (500.0, 500.0, 320.0, 240.0), 640, 480)
