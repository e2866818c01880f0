"""The depth camera's pose by hand-eye calibration: an experiment (issue 37), not a feature.

Usage::

    python scripts/hand_eye_depth_pose.py SEQ_DIR [--depth-offset-ms MS] [--points N]

Tracks SEQ_DIR (default Config, the folder's camera, depth read as it is, unregistered
where the copy's depth camera is moved: ``datasets.perturb``), pairs each keyframe with the
tracked frames nearest 4, 8, 12 and 16 deg of rotation on (``calibrate.wide_pairs``), and for
each pair aligns the two depth images alone (point-to-plane, ``depth.point_to_plane``, from
the colour motion, Huber, gates 20 / 8 / 3 px): the depth camera's motion A next to the
colour camera's B (the tracked poses, moved to the depth images' times by
``--depth-offset-ms`` at each frame's velocity). With A = X^-1 B X for X = T_color_depth,
X's rotation is the Procrustes fit of the rotation vectors (R_X a_A = a_B) and its
translation the least-squares solution of (R_B - I) t_X = R_X t_A - t_B; 1-sigma by a
bootstrap over keyframes (200 draws). Prints the pose found, its spread, and how far A
and B are apart on the same pairs (for depth registered already, as in TUM's folders, A
should equal B).
"""

from __future__ import annotations

import argparse
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax import Config
from edgevo_jax.camera import Intrinsics
from edgevo_jax.datasets.tum import load_sequence
from edgevo_jax.frontend.align import pose_start, pose_try, robust_system
from edgevo_jax.frontend.depth import depth_points, depth_valid, point_to_plane
from edgevo_jax.geometry import Pose, exp_np, inverse_np, log_np, rotation_angle_np
from edgevo_jax.pipeline.calibrate import tracked_pairs, wide_pairs


def rotvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("seq")
    p.add_argument("--depth-offset-ms", type=float, default=0.0)
    p.add_argument("--points", type=int, default=2048)
    args = p.parse_args()
    seq = load_sequence(args.seq)
    intr = Intrinsics(*(float(v) for v in seq.intrinsics))
    cfg = Config()
    t0 = time.perf_counter()
    ts, poses, pairs = tracked_pairs(seq, cfg, None)
    cand = wide_pairs(poses, pairs, (4.0, 8.0, 12.0, 16.0))
    print(f"tracked {len(ts)} frames in {time.perf_counter() - t0:.0f} s; {len(cand)} pairs")
    delta = 1e-3 * args.depth_offset_ms

    def at_depth_time(k: int) -> np.ndarray:
        v = log_np(inverse_np(poses[k - 1]) @ poses[k]) / max(ts[k] - ts[k - 1], 1e-3)
        return poses[k] @ exp_np(delta * v)

    depths: dict[int, np.ndarray] = {}

    def depth_of(k: int) -> np.ndarray:
        if k not in depths:
            depths[k] = np.asarray(seq.load_frame(k)[1], np.float32)
        return depths[k]

    pts, nrm, dep, B = [], [], [], []
    for j, i in cand:
        a, b = depth_points(depth_of(j), intr, args.points, min_depth=cfg.min_depth,
                            max_depth=cfg.max_depth, seed=j)
        pts.append(a)
        nrm.append(b)
        dep.append(depth_of(i))
        B.append(inverse_np(at_depth_time(i)) @ at_depth_time(j))  # T_ci_cj
    B = np.stack(B)

    def icp(T0, pts, nrm, depth):
        T = Pose.from_matrix(T0)
        valid = depth_valid(nrm)
        for gate in (20.0, 8.0, 3.0):
            def system_at(T, gate=gate):
                r, J, ok = point_to_plane(T, pts, nrm, depth, intr, 0)
                return robust_system(r, J, ok & (jnp.abs(r) <= gate), valid, 1.0, gate)
            state = pose_start(T, system_at(T))
            state = jax.lax.fori_loop(0, 10, lambda k, s, f=system_at: pose_try(f, s), state)
            T = state.x
        return T.as_matrix()

    A = np.asarray(jax.jit(jax.vmap(icp))(jnp.asarray(B, jnp.float32), jnp.asarray(np.stack(pts)),
                                          jnp.asarray(np.stack(nrm)), jnp.asarray(np.stack(dep))),
                   np.float64)
    aA = np.stack([rotvec(a[:3, :3]) for a in A])
    aB = np.stack([rotvec(b[:3, :3]) for b in B])

    def solve(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        U, _, Vt = np.linalg.svd(aA[keep].T @ aB[keep])
        R = Vt.T @ np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        idx = np.flatnonzero(keep)
        M = np.concatenate([B[k, :3, :3] - np.eye(3) for k in idx])
        y = np.concatenate([R @ A[k, :3, 3] - B[k, :3, 3] for k in idx])
        return R, np.linalg.lstsq(M, y, rcond=None)[0]

    keep = np.linalg.norm(aB, axis=1) > np.radians(3)
    R, t = solve(keep)
    res = np.linalg.norm(aA @ R.T - aB, axis=1)
    keep &= res < 3 * np.median(res[keep])  # drop pairs far off the first fit
    R, t = solve(keep)
    kfs = np.array([j for j, _ in cand])
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(200):
        drawn = rng.choice(np.unique(kfs[keep]), np.unique(kfs[keep]).size)
        Rb, tb = solve(keep & np.isin(kfs, drawn))
        boot.append(np.r_[np.degrees(rotvec(Rb)), 1e3 * tb])
    boot = np.array(boot)
    dR = np.degrees(rotation_angle_np(np.einsum("nji,njk->nik", A[:, :3, :3], B[:, :3, :3])))
    dt = 1e3 * np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    print(f"{keep.sum()} pairs kept over {np.unique(kfs[keep]).size} keyframes")
    spread = boot.std(0)
    print(f"rotation (deg)    {np.round(np.degrees(rotvec(R)), 2)} +- {np.round(spread[:3], 2)}")
    print(f"translation (mm)  {np.round(1e3 * t, 1)} +- {np.round(spread[3:], 1)}")
    print(f"A against B: rotation {np.median(dR):.2f} deg median ({np.percentile(dR, 90):.2f} "
          f"90th), translation {np.median(dt):.1f} mm ({np.percentile(dt, 90):.1f})")


if __name__ == "__main__":
    main()
