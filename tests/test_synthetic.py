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


@pytest.mark.slow
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


# ------------------------------------------------------------------------------ scenes


SCENE_DEPTHS = {"cluttered": (0.9, 9.5), "deep": (1.3, 45.0), "distant": (24.0, 82.0)}  # metres, every frame


def small_config(**kw):
    """A 96x72, 3-frame strong-preset sequence's settings (4 sub-frames, procedural textures)."""
    from mbavo_jax.config import PRESETS, SynthConfig

    return SynthConfig(**{**PRESETS["strong"], "frames": 3, "width": 96, "height": 72, "subframes": 4, "real_textures": False, **kw})


@pytest.mark.parametrize("scene", list(SCENE_DEPTHS))
def test_scene_renders_textured_frames_in_its_depth_range(tmp_path, scene):
    from mbavo_jax.synthetic import generate_sequence

    info = generate_sequence(small_config(scene=scene), tmp_path / scene, progress=False)
    assert info["source"] == f"synthetic {scene}" and info["mean_blur_px"] > 0
    seq = open_sequence(tmp_path / scene)
    lo, hi = SCENE_DEPTHS[scene]
    for i in range(len(seq)):
        img, depth = seq[i].image, seq[i].depth
        assert np.isfinite(img).all() and img.std() > 0.15
        blocks = img.reshape(9, 8, 12, 8).std(axis=(1, 3))
        assert (blocks < 0.01).mean() < 0.1  # texture everywhere: no large flat areas
        assert np.isfinite(depth).all() and lo < depth.min() and depth.max() < hi, (depth.min(), depth.max())
    if scene == "deep":
        assert depth.max() > 8 * depth.min()  # a wide depth range in view
    if scene == "distant":  # depth beyond 13 m needs a coarser 16-bit scale, recorded in camera.yaml
        assert seq.meta["depth_scale"] * 80 <= 65535


def test_scenes_keep_clear_of_every_preset_camera_path():
    """Camera paths of all presets stay in CAMERA_REGION, inside each enclosure and 1 m from every box."""
    import jax

    from mbavo_jax.config import PRESETS, SynthConfig
    from mbavo_jax.synthetic import SCENES, camera_path, make_scene
    from mbavo_jax.synthetic.scene import CAMERA_REGION

    assert tuple(SCENES) == SynthConfig.__dataclass_fields__["scene"].metadata["choices"]
    t = jnp.linspace(0.0, 60.0, 1201)
    for preset, values in PRESETS.items():
        cfg = SynthConfig(**values)
        for seed in (0, 1, 2):
            pos = np.asarray(jax.vmap(lambda s: camera_path(s, cfg.speed, cfg.rotation_rate, seed))(t).t)
            assert (pos >= CAMERA_REGION[0]).all() and (pos <= CAMERA_REGION[1]).all(), preset
    corners = np.array(np.meshgrid(*CAMERA_REGION.T, indexing="ij")).reshape(3, -1).T
    for name in SCENES:
        scene = make_scene(name, 0, use_real_textures=False)
        for box, inside in zip(scene.boxes, scene.inside):
            if inside:
                assert (corners > box[0] + 0.8).all() and (corners < box[1] - 0.8).all(), name
            else:
                gap = np.maximum(0.0, np.maximum(CAMERA_REGION[0] - box[1], box[0] - CAMERA_REGION[1]))
                assert np.linalg.norm(gap) >= 0.99, (name, box)


# ------------------------------------------------------------------ without exposure metadata


def assert_exposure_hidden(folder, frames):
    """``folder`` reads as TUM data: no exposure times anywhere, exposure paths kept as ground truth."""
    folder = pathlib.Path(folder)
    assert not (folder / "times.txt").exists() and not (folder / "exposure.txt").exists()
    assert (folder / "groundtruth_exposure.txt").is_file()
    cam = yaml.safe_load((folder / "camera.yaml").read_text())
    assert "exposure_ms" not in cam and {"fx", "width", "depth_scale", "response_gamma", "depth_sigma"} <= set(cam)
    seq = open_sequence(folder)
    assert seq.exposures is None and all(seq[i].exposure is None for i in range(len(seq)))
    assert seq.exposure_paths is not None and len(seq.exposure_paths[0]) == frames
    assert yaml.safe_load((folder / "synth.yaml").read_text())["exposure_info"] is False
    return seq


def test_generating_without_exposure_info(tmp_path):
    from mbavo_jax.synthetic import generate_sequence

    generate_sequence(small_config(frames=2, exposure_info=False), tmp_path / "s", progress=False)
    assert_exposure_hidden(tmp_path / "s", 2)


def test_no_exposure_info_flag(tmp_path, mbavo):
    out = tmp_path / "s"
    args = ("synth", "--preset", "mild", "--frames", 2, "--width", 64, "--height", 48, "--subframes", 2, "--out", out, "-q")
    assert mbavo(*args, "--no-exposure-info").returncode == 0
    assert_exposure_hidden(out, 2)
    assert mbavo(*args).returncode == 0  # again into the same folder, with exposure info
    assert not (out / "groundtruth_exposure.txt").exists()
    assert abs(open_sequence(out)[1].exposure - 0.020) < 1e-9


@pytest.mark.slow
def test_blurring_a_clip_without_exposure_info(tmp_path, mbavo):
    from .conftest import make_tum

    src = make_tum(tmp_path / "tum", n=3)
    out = tmp_path / "blurred"
    assert mbavo("synth", "--from", src, "--blur-px", 2, "--subframes", 4, "--no-exposure-info", "--out", out, "-q").returncode == 0
    assert_exposure_hidden(out, 3)


def test_exposure_hidden_copy_shares_the_images(tmp_path):
    from mbavo_jax.synthetic import exposure_hidden_copy, generate_sequence

    src, dst = tmp_path / "src", tmp_path / "dst"
    generate_sequence(small_config(frames=2), src, progress=False)
    for _ in range(2):  # a second copy over the first replaces it
        assert exposure_hidden_copy(src, dst) == dst
    hidden = assert_exposure_hidden(dst, 2)
    assert all((dst / sub).is_symlink() for sub in ("rgb", "depth", "sharp"))
    seq = open_sequence(src)  # the source keeps its metadata
    assert (src / "exposure.txt").is_file() and abs(seq[0].exposure - 0.025) < 1e-9
    for i in range(2):
        assert np.array_equal(seq[i].image, hidden[i].image) and np.array_equal(seq[i].depth, hidden[i].depth)
    for a, b in zip(seq.exposure_paths, hidden.exposure_paths):
        assert np.array_equal(a, b)
