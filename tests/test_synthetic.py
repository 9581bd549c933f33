"""`mbavo synth`: layout, determinism, presets, and the tie between the generator and the blur model."""

from __future__ import annotations

import hashlib
import pathlib

import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mbavo_jax.blur import plane_depths_from_keyframe, render_blurry
from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.io import read_image_gray

from .conftest import run_cli, shared_dataset


def synth(*args):
    """``mbavo synth ARGS -q`` in-process; it must succeed."""
    assert run_cli("synth", *args, "-q") == 0


@pytest.fixture(scope="module")
def strong_small(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "strong"
    synth("--preset", "strong", "--frames", 20, "--width", 160, "--height", 120, "--seed", 1, "--out", out)
    return out


@pytest.mark.slow
def test_layout(strong_small):
    d = strong_small
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "exposure.txt", "times.txt", "camera.yaml", "synth.yaml"):
        assert (d / name).is_file(), name
    for sub in ("rgb", "depth", "sharp"):
        assert len(list((d / sub).glob("*.png"))) == 20
    seq = open_sequence(d)
    assert len(seq) == 20 and seq.has_depth and seq.exposure_paths is not None
    f = seq[3]
    assert f.image.shape == (120, 160) and f.depth.dtype == np.float32 and abs(f.exposure - 0.025) < 1e-9
    cam = yaml.safe_load((d / "camera.yaml").read_text())
    assert cam["width"] == 160 and cam["response_gamma"] == 2.2
    # strong preset scales with resolution: ~20 px at 640 wide, ~5 px at 160 wide
    assert 3.0 < yaml.safe_load((d / "synth.yaml").read_text())["mean_blur_px"] < 7.0


def test_deterministic_for_a_seed(tmp_path):
    digests = []
    for k in range(2):
        out = tmp_path / f"run{k}"
        synth("--preset", "mild", "--frames", 3, "--width", 64, "--height", 48, "--subframes", 4, "--seed", 5, "--out", out)
        h = hashlib.sha256()
        for p in sorted(out.rglob("*")):
            if p.is_file() and p.name != "synth.yaml":
                h.update(p.read_bytes())
        digests.append(h.hexdigest())
    assert digests[0] == digests[1]


@pytest.mark.slow
def test_reblurring_sharp_frames_reproduces_blurry_frames(strong_small):
    """The generator (ray-cast sub-frames) and the blur model (plane transfer) agree."""
    seq = open_sequence(strong_small)
    gamma = yaml.safe_load((strong_small / "camera.yaml").read_text())["response_gamma"]
    _, starts, ends = seq.exposure_paths
    _, mids = seq.groundtruth
    for i in range(0, 20, 3):
        fr = seq[i]
        sharp = read_image_gray(pathlib.Path(fr.path).parent.parent / "sharp" / pathlib.Path(fr.path).name)
        T_mid_w = Pose.from_vector(jnp.asarray(mids[i], jnp.float32)).inverse()
        traj = ExposureTrajectory(
            T_mid_w.compose(Pose.from_vector(jnp.asarray(starts[i], jnp.float32))),
            T_mid_w.compose(Pose.from_vector(jnp.asarray(ends[i], jnp.float32))),
        )
        planes = plane_depths_from_keyframe(jnp.asarray(fr.depth), seq.camera, traj.middle())
        rb, valid = render_blurry(jnp.asarray(sharp) ** gamma, planes, seq.camera, traj, 64)
        v = np.asarray(valid)
        assert v.mean() > 0.9
        err = np.abs(np.asarray(rb) ** (1 / gamma) - fr.image)[v]
        base = np.abs(sharp - fr.image)[v]
        assert np.median(err) < 3 / 255, np.median(err)  # within 3 grey levels on most pixels
        assert np.mean(err) < 0.75 * np.mean(base), (np.mean(err), np.mean(base))


@pytest.mark.slow
def test_blurring_a_real_clip(tmp_path):
    src = shared_dataset("tum_fr1_xyz_head37")
    out = tmp_path / "tumblur"
    synth("--from", src, "--blur-px", 12, "--out", out)
    info = yaml.safe_load((out / "synth.yaml").read_text())
    assert info["frames"] == 37 and abs(info["mean_blur_px"] - 12) < 1.5
    seq = open_sequence(out)
    t_gt, _ = seq.groundtruth
    assert len(t_gt) == 37 and seq.has_depth
    # blurry differs from sharp, and the ground truth is the real clip's mid-exposure pose
    f = seq[5]
    sharp = read_image_gray(pathlib.Path(f.path).parent.parent / "sharp" / pathlib.Path(f.path).name)
    assert np.mean(np.abs(sharp - f.image)) > 0.01


def test_sensor_depth_model():
    """Kinect-class depth: noise σ(z) = a + b (z − 0.4)², spatially correlated, holes on depth edges."""
    from mbavo_jax.synthetic import sensor_depth

    rng = np.random.default_rng(0)
    depth = np.full((120, 160), 3.0, np.float32)
    depth[:, 80:] = 4.0
    depth[:5, :5] = 0.0  # no surface
    noisy = sensor_depth(depth, rng)
    assert noisy[:5, :5].max() == 0.0
    assert (noisy[:, 79:81] == 0).all()  # the edge is a hole
    flat = noisy[10:-10, 10:70]
    ok = flat > 0
    assert 0.95 < ok.mean() < 1.0  # 1 % random dropouts
    sigma = 0.0012 + 0.0019 * (3.0 - 0.4) ** 2
    assert abs(flat[ok].std() / sigma - 1) < 0.3 and abs(flat[ok].mean() - 3.0) < 0.3 * sigma
    right = noisy[10:-10, 90:-10]
    assert right[right > 0].std() > 1.5 * flat[ok].std()  # grows with depth
    corr = np.corrcoef(flat[:, :-1][ok[:, :-1] & ok[:, 1:]], flat[:, 1:][ok[:, :-1] & ok[:, 1:]])[0, 1]
    assert corr > 0.5  # neighbours share their error


def test_depth_model_recorded_in_camera_yaml(tmp_path):
    out = tmp_path / "s"
    synth("--preset", "mild", "--frames", 2, "--width", 64, "--height", 48, "--out", out, "--no-real-textures", "--depth-model", "sensor")
    seq = open_sequence(out)
    assert seq.meta["depth_sigma"] == [0.0012, 0.0019]
    assert (seq[0].depth == 0).any() or np.isnan(seq[0].depth).any()  # holes
