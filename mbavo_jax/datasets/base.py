"""The frame type every loader returns, and the lazy sequence."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Callable

import numpy as np

from ..errors import FrameIndexError
from ..geometry.camera import PinholeCamera
from ..imu.data import ImuData
from ..io import ExposureRows, check_size
from .distortion import CameraModel

__all__ = ["Frame", "Sequence"]


@dataclasses.dataclass(frozen=True)
class Frame:
    """One image of a sequence.

    ``image``: float32 grey in [0, 1], shape (H, W). ``depth``: float32 metres (NaN = none) or None.
    ``timestamp``: seconds, mid-exposure. ``exposure``: exposure time in seconds, or None.
    """

    index: int
    timestamp: float
    image: np.ndarray
    camera: PinholeCamera
    depth: np.ndarray | None = None
    exposure: float | None = None
    path: str = ""


@dataclasses.dataclass
class Sequence:
    """A lazily loaded sequence. ``frame_loader(i)`` reads frame i from disk on demand; ``seq[i]``
    also checks that its image has the camera's size (loaders leave that check to it).

    ``groundtruth``: (stamps (M,), poses (M, 7) [t, q], camera-to-world) or None.
    ``exposure_paths``: (stamps, start (N, 7), end (N, 7)) camera-to-world, or None.
    ``exposure_rows``: per-row exposure paths of a rolling-shutter sequence (``exposure_rows.txt``), or None.
    ``lens``: the camera its calibration file describes, when its images are undistorted at load into
    ``camera`` (:mod:`~mbavo_jax.datasets.distortion`); None: ``camera`` is the calibration itself.
    ``imu``: the IMU's samples, calibration and noise figures (:class:`~mbavo_jax.imu.data.ImuData`;
    our ``imu.txt`` with camera.yaml's ``imu:`` block, EuRoC's ``mav0/imu0``), or None.
    """

    name: str
    path: pathlib.Path
    camera: PinholeCamera
    timestamps: np.ndarray
    frame_loader: Callable[[int], Frame]
    exposures: np.ndarray | None = None
    groundtruth: tuple[np.ndarray, np.ndarray] | None = None
    exposure_paths: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    has_depth: bool = False
    kind: str = ""
    meta: dict = dataclasses.field(default_factory=dict)  # e.g. camera.yaml extras: response_gamma
    exposure_rows: ExposureRows | None = None
    lens: CameraModel | None = None
    imu: ImuData | None = None

    @property
    def camera_model(self) -> dict:
        """The lens model its calibration gives (what ``mbavo info`` and run.yaml record):
        ``{"model": "pinhole"}``, or the model, its coefficients and the intrinsics and size it was
        calibrated at (the images undistorted at load into ``camera``)."""
        return {"model": "pinhole"} if self.lens is None else self.lens.describe()

    @property
    def readout_s(self) -> float:
        """Rolling-shutter readout time (s) from the first row's exposure start to the last row's:
        camera.yaml's ``readout_ms``; 0 (a global shutter) when it records none."""
        return float(self.meta.get("readout_ms", 0.0)) / 1000.0

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not -n <= i < n:
            raise FrameIndexError(f"{self.path}: frame {i} out of range (the sequence has {n} frames, 0 to {n - 1})")
        frame = self.frame_loader(i % n)
        check_size(frame.path, frame.image, (self.camera.height, self.camera.width))
        return frame

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
