"""Generated blurry sequences with ground-truth exposure paths (``mbavo synth``).

``SynthConfig``, ``PRESETS`` and ``DEPTH_SIGMA`` live in :mod:`mbavo_jax.config`; they are re-exported here."""

from ..config import DEPTH_SIGMA, PRESETS, SynthConfig
from .generator import blur_real_sequence, camera_path, generate_sequence, mean_blur_length, sensor_depth
from .scene import Scene, default_scene, render_exposure, scene_arrays

__all__ = [
    "PRESETS",
    "SynthConfig",
    "generate_sequence",
    "blur_real_sequence",
    "camera_path",
    "mean_blur_length",
    "sensor_depth",
    "DEPTH_SIGMA",
    "Scene",
    "default_scene",
    "render_exposure",
    "scene_arrays",
]
