"""Evaluation: association, Umeyama round trips, APE/RPE against evo, frame drops, exposure error."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.evaluation import ape, associate, exposure_path_error, frame_drop_rate, rpe, umeyama
from mbavo_jax.evaluation.metrics import pose_matrices
from mbavo_jax.io import write_exposure_file, write_tum_trajectory


def random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return pose_matrices(np.r_[np.zeros(3), q][None])[0][:3, :3], q


def smooth_trajectory(n=60, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6, n)
    xyz = np.stack([np.sin(t), 0.5 * np.cos(0.7 * t), 0.3 * t], 1)
    qs = []
    for k in range(n):
        a = 0.3 * np.sin(0.5 * t[k])
        qs.append([0, np.sin(a / 2), 0, np.cos(a / 2)])
    return 100.0 + t, np.concatenate([xyz, np.array(qs)], 1), rng


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_round_trip(with_scale):
    stamps, poses, rng = smooth_trajectory()
    R, _ = random_rotation(rng)
    s = 2.5 if with_scale else 1.0
    t = rng.normal(size=3)
    moved = s * poses[:, :3] @ R.T + t
    R2, t2, s2 = umeyama(poses[:, :3], moved, with_scale)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    assert abs(s2 - s) < 1e-9


def test_transform_then_align_back_gives_zero_error():
    stamps, poses, rng = smooth_trajectory()
    R, q = random_rotation(rng)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
    Ts = T @ pose_matrices(poses)
    from mbavo_jax.geometry.quaternion import from_matrix

    moved = np.array([np.r_[M[:3, 3], np.asarray(from_matrix(jnp.asarray(M[:3, :3])))] for M in Ts])
    assert ape(stamps, poses, stamps, moved, "se3")["rmse"] < 1e-6
    assert rpe(stamps, poses, stamps, moved)["rmse"] < 1e-6


def test_association_and_frame_drops():
    ref = np.arange(10) * 0.1
    est = np.array([0.001, 0.205, 0.3, 0.7009, 5.0])
    i_est, i_ref = associate(est, ref, 0.01)
    assert list(i_est) == [0, 1, 2, 3] and list(i_ref) == [0, 2, 3, 7]
    assert frame_drop_rate(ref, est, 0.01) == pytest.approx(0.6)


def _write_pair(tmp_path, seed=1, scale=1.0):
    stamps, poses, rng = smooth_trajectory(seed=seed)
    est = poses.copy()
    est[:, :3] = scale * est[:, :3] + rng.normal(scale=0.02, size=(len(poses), 3))
    R, _ = random_rotation(rng)
    est[:, :3] = est[:, :3] @ R.T + 1.0
    from mbavo_jax.geometry.quaternion import from_matrix

    est[:, 3:] = [np.asarray(from_matrix(jnp.asarray(R @ pose_matrices(p[None])[0][:3, :3]))) for p in est]
    ref_path, est_path = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum_trajectory(ref_path, stamps, poses)
    write_tum_trajectory(est_path, stamps + 0.003, est)
    return ref_path, est_path


@pytest.mark.parametrize("align,scale", [("se3", 1.0), ("sim3", 0.5)])
def test_ape_agrees_with_evo(tmp_path, align, scale, mbavo):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref_path, est_path = _write_pair(tmp_path, scale=scale)
    out = mbavo("eval", "ape", ref_path, est_path, "--align", align, "--format", "json")
    assert out.returncode == 0, out.stderr
    ours = json.loads(out.stdout)
    traj_ref = file_interface.read_tum_trajectory_file(str(ref_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    traj_est.align(traj_ref, correct_scale=align == "sim3")
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((traj_ref, traj_est))
    theirs = m.get_all_statistics()
    assert ours["n_matched"] == traj_ref.num_poses
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        assert abs(ours[k] - theirs[k]) < 1e-6, (k, ours[k], theirs[k])


def test_rpe_agrees_with_evo(tmp_path, mbavo):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref_path, est_path = _write_pair(tmp_path, seed=3)
    out = mbavo("eval", "rpe", ref_path, est_path, "--format", "json")
    assert out.returncode == 0, out.stderr
    ours = json.loads(out.stdout)
    traj_ref = file_interface.read_tum_trajectory_file(str(ref_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    m = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
    m.process_data((traj_ref, traj_est))
    theirs = m.get_all_statistics()
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        assert abs(ours[k] - theirs[k]) < 1e-6, (k, ours[k], theirs[k])


@pytest.mark.slow
def test_exposure_path_error(tmp_path, mbavo):
    stamps, poses, rng = smooth_trajectory(10)
    poses[:, 3:] = [0, 0, 0, 1]  # unrotated cameras: a world-x shift is a camera-x shift
    starts, ends = poses.copy(), poses.copy()
    starts[:, 0] -= 0.01
    ends[:, 0] += 0.01
    cam = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    same = exposure_path_error((stamps, starts, ends), (stamps, starts, ends), cam)
    assert same["reprojection_px"]["max"] < 1e-9 and same["n_matched"] == 10
    wrong = exposure_path_error((stamps, starts, ends), (stamps, poses, poses), cam, depth=2.0)
    # estimated start and end collapsed onto the mid pose: each is 1 cm off, 2.5 px at 2 m (f = 500)
    assert wrong["translation_m"]["mean"] == pytest.approx(0.01, abs=1e-9)
    assert wrong["reprojection_px"]["mean"] == pytest.approx(2.5, abs=1e-6)
    write_exposure_file(tmp_path / "a.txt", stamps, starts, ends)
    (tmp_path / "cam.yaml").write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\n")
    out = mbavo("eval", "exposure", tmp_path / "a.txt", tmp_path / "a.txt", "--camera", tmp_path / "cam.yaml", "--format", "json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["reprojection_px"]["max"] < 1e-9


def test_plots_are_written(tmp_path, mbavo):
    ref_path, est_path = _write_pair(tmp_path)
    assert mbavo("eval", "ape", ref_path, est_path, "--plot", tmp_path / "plots").returncode == 0
    for name in ("trajectory.png", "ape_over_time.png"):
        data = (tmp_path / "plots" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
