"""Generated blurry sequences with ground-truth exposure paths (``mbavo synth``).

``SynthConfig``, ``PRESETS`` and ``DEPTH_SIGMA`` live in :mod:`mbavo_jax.config`; they are re-exported here."""

from ..config import DEPTH_SIGMA, PRESETS, SynthConfig
from .generator import (blur_real_sequence, camera_path, depth_scale, generate_sequence, mean_blur_length, path_bend, sampled_rows,
                        sensor_depth)
from .metadata import EXPOSURE_ROWS, exposure_hidden_copy, hide_exposure_info
from .scene import SCENES, Scene, default_scene, make_scene, render_exposure, render_rolling_exposure, scene_arrays

__all__ = [
    "PRESETS",
    "SynthConfig",
    "generate_sequence",
    "blur_real_sequence",
    "camera_path",
    "mean_blur_length",
    "path_bend",
    "sampled_rows",
    "EXPOSURE_ROWS",
    "sensor_depth",
    "depth_scale",
    "hide_exposure_info",
    "exposure_hidden_copy",
    "DEPTH_SIGMA",
    "Scene",
    "default_scene",
    "make_scene",
    "SCENES",
    "render_exposure",
    "render_rolling_exposure",
    "scene_arrays",
]
