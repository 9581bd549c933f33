"""Generated scenes unlike the rooms: one plane seen obliquely (``scene: plane``), photo-like
dead-leaves textures (``texture: photo``), a target mean blur (``blur_px``), and the named scene
sequences of the benchmarks (``plane_b10`` ...)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mbavo_jax.bench.sequences import scene_settings
from mbavo_jax.cli import build_parser
from mbavo_jax.config import PRESETS, SynthConfig, from_arguments
from mbavo_jax.errors import ConfigError, MbavoError
from mbavo_jax.geometry import PinholeCamera, Pose
from mbavo_jax.synthetic import generate_sequence
from mbavo_jax.synthetic.scene import CAMERA_CENTRE, PLANE_DISTANCE, dead_leaves, make_scene, render_exposure, scene_arrays


def _camera(width: int, height: int) -> PinholeCamera:
    f = 525.0 * width / 640.0
    return PinholeCamera.create(f, f, (width - 1) / 2, (height - 1) / 2, width, height)


def test_the_plane_scene_is_one_oblique_plane():
    """From the camera paths' centre every pixel sees one plane (its back-projected depth fits a
    plane to 1 mm, nothing farther than 20 m), PLANE_DISTANCE ahead, its normal 25-40 deg from the
    view axis, so that depth changes across the view."""
    cam = _camera(80, 60)
    pose = Pose(jnp.array([0.0, 0.0, 0.0, 1.0]), jnp.asarray(CAMERA_CENTRE, jnp.float32))
    _, _, depth = render_exposure(scene_arrays(make_scene("plane", 0, use_real_textures=False)), cam,
                                  jax.tree_util.tree_map(lambda a: a[None], pose), pose)
    z = np.asarray(depth, np.float64)
    v, u = np.mgrid[0:60, 0:80]
    pts = np.stack([(u - float(cam.cx)) / float(cam.fx) * z, (v - float(cam.cy)) / float(cam.fy) * z, z], -1).reshape(-1, 3)
    centre = pts.mean(0)
    normal = np.linalg.svd(pts - centre)[2][-1]
    assert z.max() < 20.0 and np.abs((pts - centre) @ normal).max() < 1e-3
    assert 25.0 < np.degrees(np.arccos(abs(normal[2]))) < 40.0
    assert abs(centre @ normal) == pytest.approx(PLANE_DISTANCE, abs=0.01)
    assert z.max() - z.min() > 1.0


def _amplitude_slope(img: np.ndarray, lo: int, hi: int) -> float:
    """Slope of log radial mean |FFT| against log frequency (cycles per image) over [lo, hi]."""
    n = img.shape[0]
    spectrum = np.abs(np.fft.fft2(img - img.mean()))
    f = np.fft.fftfreq(n) * n
    radius = np.hypot(*np.meshgrid(f, f))
    bins = np.arange(lo, hi + 1)
    amplitude = [spectrum[np.abs(radius - b) < 0.5].mean() for b in bins]
    return float(np.polyfit(np.log(bins), np.log(amplitude), 1)[0])


def test_photo_textures_have_a_natural_spectrum():
    """Dead leaves: amplitude ∝ 1/f (slope -1 within 0.25) over 4-32 cycles, as natural images
    (white noise: 0; the procedural value noise: about -2); photo puts them on every surface."""
    tex = dead_leaves(np.random.default_rng(0), 256)
    assert tex.shape == (256, 256) and tex.min() >= 0 and tex.max() <= 1
    assert -1.25 < _amplitude_slope(tex, 4, 32) < -0.75
    scene = make_scene("room", 0, texture="photo")
    assert set(scene.texture_names) == {"photo"} and scene.texture.max() < len(scene.textures)
    with pytest.raises(ValueError, match="unknown texture 'foto'"):
        make_scene("room", 0, texture="foto")


def test_the_new_settings_parse_and_check():
    """`mbavo synth --scene plane --texture photo --blur-px 10` builds those settings on the preset;
    out-of-range values are refused in one line."""
    args = build_parser().parse_args(["synth", "--out", "x", "--scene", "plane", "--texture", "photo", "--blur-px", "10"])
    cfg = from_arguments(SynthConfig, args, PRESETS[args.preset])
    assert (cfg.scene, cfg.texture, cfg.blur_px, cfg.speed) == ("plane", "photo", 10.0, PRESETS["strong"]["speed"])
    assert SynthConfig(**{**cfg.__dict__}) == cfg
    with pytest.raises(ConfigError, match="texture: must be one of mixed, photo"):
        SynthConfig(texture="foto")
    with pytest.raises(ConfigError, match="blur_px: must be >= 0"):
        SynthConfig(blur_px=-1.0)
    with pytest.raises(ConfigError, match="needs subframes > 1"):
        SynthConfig(blur_px=5.0, subframes=1)


@pytest.mark.slow
def test_a_target_blur_is_reached_by_the_exposure(tmp_path):
    """blur_px scales the exposure (the motion kept) until the sequence's mean blur is the target
    (within 15 %); synth.yaml records the settings; a blur beyond the frame interval is refused."""
    base = dict(PRESETS["strong"], frames=4, width=160, height=120, subframes=16, seed=0, real_textures=False, scene="plane",
                texture="photo")
    summary = generate_sequence(SynthConfig(**base, blur_px=3.0), tmp_path / "b3", progress=False)
    assert summary["mean_blur_px"] == pytest.approx(3.0, rel=0.15)
    written = yaml.safe_load((tmp_path / "b3" / "synth.yaml").read_text())["config"]
    assert (written["scene"], written["texture"], written["blur_px"]) == ("plane", "photo", 3.0)
    assert written["exposure_ms"] != PRESETS["strong"]["exposure_ms"]
    with pytest.raises(ConfigError, match="longer than the frame interval"):
        generate_sequence(SynthConfig(**base, blur_px=60.0), tmp_path / "b60", progress=False)
    assert not (tmp_path / "b60").exists()  # refused before any file is written


def test_named_scene_sequences_of_the_benchmarks():
    """<scene>[_photo]_b<px>[_<preset>]: the scene, textures, target blur and motion; b0 is sharp."""
    assert scene_settings("plane_b10") == {**PRESETS["strong"], "blur_px": 10.0, "subframes": 64, "scene": "plane", "texture": "mixed"}
    named = scene_settings("plane_photo_b20_extreme")
    assert (named["texture"], named["blur_px"], named["speed"]) == ("photo", 20.0, PRESETS["extreme"]["speed"])
    assert scene_settings("room_b0")["exposure_ms"] == 0.0 and "blur_px" not in scene_settings("room_b0")
    assert scene_settings("strong") is None
    with pytest.raises(MbavoError, match="unknown scene or motion preset"):
        scene_settings("wall_b10")
