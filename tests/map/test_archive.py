"""map.archive: a keyframe map saved and loaded back the same, bit for bit; every file that
does not fit (not a map, another version, truncated, corrupt, another camera or settings)
refused with a MapFileError naming the problem; a failed save leaves the old file."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.map import archive
from edgevo_jax.map.archive import MapFileError, load_map, read_header, save_map
from edgevo_jax.runs.run import run_sequence

SETTINGS = archive.map_settings(Config())


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The bundled clip's keyframe map, saved once: (sequence, map, file)."""
    seq = load_sequence(BUNDLED_CLIP)
    kept = {}
    run_sequence(seq, Config(), progress=False,
                 on_frame=lambda result, rgb, frame, odo: kept.__setitem__("odo", odo))
    odo = kept["odo"]
    odo.finish()
    kmap = odo.keyframe_map
    path = tmp_path_factory.mktemp("map") / "bundled.npz"
    odo.save_map(path)  # with the pose graph's edges
    return seq, kmap, path


def load(path, seq, **kw) -> archive.Saved:
    return load_map(path, intrinsics=kw.pop("intrinsics", seq.intrinsics),
                    shape=kw.pop("shape", (seq.height, seq.width)),
                    settings=kw.pop("settings", SETTINGS), max_keyframes=100, **kw)


def test_a_map_saved_and_loaded_is_the_same_and_saves_to_the_same_bytes(made, tmp_path):
    seq, kmap, path = made
    saved = load(path, seq)
    back = saved.kmap
    assert back.ids == kmap.ids and len(back) >= 2
    for key in kmap.ids:
        a, b = kmap[key], back[key]
        np.testing.assert_array_equal(a.pose, b.pose)
        assert a.timestamp == b.timestamp and a.anchored == b.anchored and a.share == b.share
        assert (a.code is None) == (b.code is None)
        if a.code is not None:
            np.testing.assert_array_equal(a.code, b.code)
        for x, y in zip(a.edges, b.edges, strict=True):
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(np.asarray(x), y)
        np.testing.assert_array_equal(a.points, b.points)
        assert kmap.covisible(key) == back.covisible(key)
    # the pose graph: each keyframe but the first tied to its parent, measured
    assert sorted(e.j for e in saved.edges) == kmap.ids[1:]
    for e in saved.edges:
        assert not e.loop and e.i < e.j and e.information.shape == (6, 6)
        np.testing.assert_allclose(e.measured, np.linalg.inv(back[e.i].pose) @ back[e.j].pose,
                                   atol=1e-9)
    again = tmp_path / "again.npz"
    save_map(again, back, settings=SETTINGS, library=read_header(path)["library"],
             edges=saved.edges)
    assert again.read_bytes() == path.read_bytes()
    header = read_header(path)
    assert header["keyframes"] == len(kmap) and header["version"] == archive.VERSION


def test_files_that_are_no_map_or_damaged_are_refused_by_name(made, tmp_path):
    seq, _, path = made
    data = path.read_bytes()
    cases = {
        "missing.npz": (None, "no such map file"),
        "text.npz": (b"not a map at all", "not a map file"),
        "truncated.npz": (data[: len(data) // 2], "truncated or corrupt"),
    }
    corrupt = bytearray(data)
    corrupt[len(data) // 3: len(data) // 3 + 64] = b"\xff" * 64  # inside an array's bytes
    cases["corrupt.npz"] = (bytes(corrupt), "truncated or corrupt|cannot be read|header")
    for name, (content, words) in cases.items():
        target = tmp_path / name
        if content is not None:
            target.write_bytes(content)
        with pytest.raises(MapFileError, match=words) as err:
            load(target, seq)
        assert str(target) in str(err.value)
    other = tmp_path / "other.npz"
    np.savez(other, something=np.zeros(3))
    with pytest.raises(MapFileError, match="no 'header' array"):
        load(other, seq)


def rewritten(path: Path, out: Path, **changes) -> Path:
    """The map at ``path`` with its header's keys changed."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    header = json.loads(bytes(arrays["header"]).decode())
    header.update(changes)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(out, **arrays)
    return out


def test_another_version_camera_or_settings_is_refused_before_any_keyframe(made, tmp_path):
    seq, _, path = made
    with pytest.raises(MapFileError, match="format version 3; .* reads versions 1, 2"):
        load(rewritten(path, tmp_path / "v3.npz", version=3), seq)
    # version 1 had no pose graph: read with none
    assert load(rewritten(path, tmp_path / "v1.npz", version=1), seq).edges == []
    with pytest.raises(MapFileError, match="not an edgevo map file"):
        load(rewritten(path, tmp_path / "fmt.npz", format="something"), seq)
    other = seq.intrinsics._replace(fx=seq.intrinsics.fx + 5.0)
    with pytest.raises(MapFileError, match="another camera"):
        load(path, seq, intrinsics=other)
    with pytest.raises(MapFileError, match="640x480 images, this run's are 320x240"):
        load(path, seq, shape=(240, 320))
    with pytest.raises(MapFileError, match="depth_points 256 in the map, 128 here"):
        load(path, seq, settings={**SETTINGS, "depth_points": 128})


def test_a_failed_save_leaves_the_old_file_and_no_litter(made, tmp_path, monkeypatch):
    seq, kmap, path = made
    target = tmp_path / "kept.npz"
    target.write_bytes(path.read_bytes())

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(archive.np, "savez", broken)
    with pytest.raises(OSError, match="disk full"):
        save_map(target, kmap, settings=SETTINGS, library="test")
    assert target.read_bytes() == path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.npz"]
    assert zipfile.is_zipfile(target)


def test_saving_mid_run_changes_no_pose(tmp_path):
    """The streaming API saves the map at any frame and the run goes on as it would have:
    every pose the same, bit for bit, as a run that never saved."""
    seq = load_sequence(BUNDLED_CLIP)

    def poses(save: bool) -> np.ndarray:
        from edgevo_jax.tracking.odometry import Odometry

        with Odometry(Config(), seq.intrinsics) as odo:
            for i in range(len(seq)):
                rgb, depth = seq.load_frame(i)
                odo.track(rgb, depth, float(seq.timestamps[i]))
                if save and odo.has_keyframe:
                    odo.save_map(tmp_path / f"at{i}.npz")
            odo.finish()
            return odo.poses()

    np.testing.assert_array_equal(poses(True), poses(False))
    assert len(list(tmp_path.glob("at*.npz"))) == len(seq)


def test_the_command_line_saves_the_map_and_map_info_reads_it(tmp_path, capsys):
    from edgevo_jax.cli import main

    out, saved = tmp_path / "traj.txt", tmp_path / "maps" / "bundled.npz"
    assert main(["run", "--out", str(out), "--save-map", str(saved), "--no-progress"]) == 0
    header = read_header(saved)
    assert header["keyframes"] >= 2 and header["camera"]["width"] == 640
    assert f"map           {saved}" in capsys.readouterr().out
    assert main(["map", "info", str(saved)]) == 0
    text = capsys.readouterr().out
    assert f"keyframes     {header['keyframes']} " in text and "fx 517.3" in text
    stats = tmp_path / "stats.json"
    assert main(["run", "--out", str(out), "--map", str(saved), "--stats", str(stats),
                 "--no-progress"]) == 0  # the same clip again, in its own map: found
    assert json.loads(stats.read_text())["map"]["found_in_loaded"] is not None
    assert "found in it at frame" in capsys.readouterr().out
    assert main(["map", "info", str(out)]) == 2  # a trajectory file is no map
    assert "not a map file" in capsys.readouterr().err
    # with the map off there is nothing to save: said before any frame is tracked
    assert main(["run", "--out", str(out), "--save-map", str(saved), "--no-progress",
                 "--set", "map=false"]) == 2
    assert "Config.map is off" in capsys.readouterr().err


def test_a_run_in_a_saved_map_is_found_in_it_and_written_in_its_frame(tmp_path, monkeypatch):
    """The bundled clip's first 5 frames make a map; its last 5, started at the identity in
    that map, are WEAK (not tied to it) until a frame is found in it, then in its frame:
    the frame both runs share lands where the first run put it; the new keyframes join the
    map, and a second load of the same file gives the same trajectory. The first frame
    tracked asks on the tracker's thread; where it finds nothing (made to, here), the next
    frames ask beside tracking, each query taken ``map_query_lag`` frames later."""
    from edgevo_jax.datasets.tum import subsequence
    from edgevo_jax.geometry import inverse_np, rotation_angle_np
    from edgevo_jax.tracking import places

    seq = load_sequence(BUNDLED_CLIP)
    first, second = subsequence(seq, 0, 5), subsequence(seq, 4, len(seq))
    saved, grown = tmp_path / "first.npz", tmp_path / "grown.npz"
    one = run_sequence(first, Config(), progress=False, save_map=saved)
    config = Config(map_query_lag=2)  # the second session is 5 frames long

    def run_second():
        from edgevo_jax.tracking.odometry import Odometry

        with Odometry(config, seq.intrinsics, map_file=saved) as odo:
            results = []
            for i in range(len(second)):
                rgb, depth = second.load_frame(i)
                results.append(odo.track(rgb, depth, float(second.timestamps[i])))
            odo.finish()
            odo.save_map(grown)
            return results, odo.poses(), odo.found_in_loaded

    def check(results, poses, found) -> None:
        assert all(r.state == "WEAK" and "not tied to the map" in r.reason
                   for r in results[:found])
        assert results[found].state == "OK", [(r.state, r.reason) for r in results]
        D = inverse_np(one.poses[4]) @ poses[0]  # frame 4 of the clip, in both runs
        assert np.linalg.norm(D[:3, 3]) < 0.02 and np.degrees(rotation_angle_np(D)) < 2.0

    results, poses, found = run_second()
    assert found == 1 and results[1].placed.startswith("found again")  # on the thread
    check(results, poses, found)
    assert read_header(grown)["keyframes"] > read_header(saved)["keyframes"]
    again, poses_again, found_again = run_second()
    np.testing.assert_array_equal(poses_again, poses)
    assert found_again == found
    # the first query finds nothing: frame 2's, beside tracking, is taken at frame 4
    calls = []
    real = places.place

    def first_fails(*args, **kwargs):
        calls.append(kwargs["label"])
        return None if len(calls) == 1 else real(*args, **kwargs)

    monkeypatch.setattr(places, "place", first_fails)
    results, poses, found = run_second()
    assert calls[:2] == ["found again", "found in the loaded map"]
    assert found == 2 + config.map_query_lag
    assert results[found].placed.startswith("found in the loaded map: keyframe ")
    assert "at frame 2, beside tracking" in results[found].placed
    check(results, poses, found)


def test_a_map_exported_as_a_point_cloud_holds_its_edges_where_the_map_puts_them(
        made, tmp_path, capsys):
    """``edgevo map export``: a binary PLY any viewer reads, one point per edge point of
    each keyframe, at the keyframe's pose in the map's frame, coloured by keyframe time;
    ``--max-depth`` keeps the nearer ones; not a map: exit 2 naming it."""
    from edgevo_jax.cli import main
    from edgevo_jax.map.export import RAMP, map_cloud

    _, kmap, path = made
    out = tmp_path / "cloud.ply"
    assert main(["map", "export", str(path), str(out)]) == 0
    data = out.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    n = int(next(line for line in head.decode().splitlines()
                 if line.startswith("element vertex")).split()[-1])
    rows = np.frombuffer(body, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"),
                                ("g", "u1"), ("b", "u1")])
    assert len(rows) == n == sum(kmap[k].points.shape[1] for k in kmap.ids) > 100
    assert f"wrote {out} ({n:,} points)" in capsys.readouterr().out
    last = kmap[kmap.ids[-1]]
    world = (last.pose[:3, :3] @ last.points.astype(np.float64) + last.pose[:3, 3:]).T
    tail = np.stack([rows["x"], rows["y"], rows["z"]], axis=1)[-len(world):]
    np.testing.assert_allclose(tail, world, atol=1e-5)
    rgb = np.stack([rows["r"], rows["g"], rows["b"]], axis=1)
    assert tuple(rgb[0]) == RAMP[0][1] and tuple(rgb[-1]) == RAMP[-1][1]
    near = map_cloud(path, max_depth=1.0)
    assert 0 < len(near.xyz) < n
    assert main(["map", "export", str(path), str(tmp_path / "cloud.txt")]) == 2
    assert main(["map", "export", str(out), str(tmp_path / "again.ply")]) == 2
    assert "not a map file" in capsys.readouterr().err
    picture = tmp_path / "map.png"
    assert main(["plot", "map", str(path), "--out", str(picture)]) == 0
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
