"""Generated blurry sequences with ground-truth exposure paths (``mbavo synth``)."""

from .generator import DEPTH_SIGMA, PRESETS, SynthConfig, blur_real_sequence, camera_path, generate_sequence, mean_blur_length, sensor_depth
from .scene import Scene, default_scene, render, render_exposure, scene_arrays

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
    "render",
    "render_exposure",
    "scene_arrays",
]
