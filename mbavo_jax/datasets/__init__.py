"""Dataset loaders with one frame type. Loading is lazy: a sequence reads a frame when it is indexed.

``open_sequence(path)`` detects the layout: TUM RGB-D (``rgb.txt``; also what ``mbavo synth`` writes),
KITTI odometry (``calib.txt`` + ``times.txt``), EuRoC (``mav0/cam0/data.csv``), DSO-style
(``times.txt`` with ``id timestamp exposure_ms`` + ``camera.txt``), or a plain image folder with
``camera.yaml``. Image folders are listed in natural order (``frame2`` before ``frame10``). A lens
with distortion (EuRoC's sensor.yaml, DSO's camera.txt, TUM fr1/fr2) is undistorted at load into a
pinhole camera (:mod:`~mbavo_jax.datasets.distortion`); ``Sequence.camera_model`` says which it was.
"""

from .base import Frame, Sequence
from .loaders import open_sequence, open_dso, open_euroc, open_image_folder, open_kitti, open_tum

__all__ = [
    "Frame",
    "Sequence",
    "open_sequence",
    "open_tum",
    "open_kitti",
    "open_euroc",
    "open_dso",
    "open_image_folder",
]
