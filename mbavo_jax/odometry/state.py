"""The state a sequence loop carries from frame to frame, and what one frame's step produces.

A pipeline (the RGB-D one in ``odometry.rgbd``; a monocular one plugs in the same way) is an
object with ``step(state, frame) -> (state, outcome)``: a pure function of its inputs that does no
file I/O. ``odometry.outputs`` writes outcomes, ``odometry.run`` drives the loop and resumes it.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import RunConfig
from ..geometry import ExposurePath, Pose
from ..tracking import Keyframe, TrackResult
from .exposure import ExposureEstimate, RawFrame

__all__ = ["Fit", "KeyframeState", "PendingDeblur", "RunState", "NewKeyframe", "Triptych", "ExposureReport", "FrameOutcome", "Pairing", "Pipeline"]


@dataclasses.dataclass(frozen=True)
class Fit:
    """How well a tracked frame fitted: its residual RMS and how far (mean px) its pose lay from the
    constant-velocity prediction (None: there was no velocity to predict with)."""

    rms: float
    jump_px: float | None


@dataclasses.dataclass(frozen=True)
class KeyframeState:
    """The keyframe frames are tracked against: its points and pyramid, its pose, its stamp."""

    keyframe: Keyframe
    T_world_kf: Pose
    stamp: float


@dataclasses.dataclass(frozen=True)
class PendingDeblur:
    """A keyframe made without an exposure path (the first frame, a reset after drops): its raw
    image, depth and exposure time (None: estimated), until the next tracked frame gives the
    camera's velocity."""

    image: np.ndarray
    depth: np.ndarray
    exposure: float | None


@dataclasses.dataclass(frozen=True)
class RunState:
    """Everything the loop carries between frames."""

    keyframe: KeyframeState | None = None
    mids: tuple[tuple[float, Pose], ...] = ()  # the last (up to two) tracked (stamp, T_world_mid)
    pending: PendingDeblur | None = None
    tracked: int = 0
    dropped: int = 0
    consecutive_drops: int = 0
    keyframes: int = 0
    triptychs: int = 0
    exposure: ExposureEstimate | None = None  # when the exposure time is estimated
    recent: tuple[RawFrame, ...] = ()  # the last raw frames, for the estimate's pairs
    probed_until: float = float("-inf")  # the exposure probe's last frame: the samples of frames up to it are in ``exposure``
    fits: tuple[Fit, ...] = ()  # the last accepted frames' fits, for the plausibility checks
    backend: object | None = None  # the monocular system's window and initialiser (odometry.mono.MonoState)

    def replace(self, **changes) -> "RunState":
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class Triptych:
    """What the blurry / reblurred / deblurred picture of a new keyframe is drawn from."""

    blurry: np.ndarray
    sharp: np.ndarray
    depth: np.ndarray
    path: ExposurePath  # the frame's exposure path (any reference frame)
    n: int  # virtual frames the deblurring used
    readout: float = 0.0  # the frame's rolling-shutter readout fraction (blur.render_blurry's ``readout``)


@dataclasses.dataclass(frozen=True)
class NewKeyframe:
    """A keyframe made at this frame (its image: deblurred where it was)."""

    stamp: float
    T_world_kf: Pose
    image: np.ndarray
    triptych: Triptych | None = None


@dataclasses.dataclass(frozen=True)
class Pairing:
    """What a tracked frame gave the estimated exposure's pairing: the raw frames kept, a sample
    (exposure s, weight) or None, and the previous raw frame's central speed (px/s), which this
    frame completes (None when it does not follow that frame directly)."""

    recent: tuple[RawFrame, ...]
    sample: tuple[float, float] | None = None
    completed_speed: float | None = None


@dataclasses.dataclass(frozen=True)
class ExposureReport:
    """A frame's exposure time: how it is known (``known``, ``estimate``, ``none``), its value
    after this frame (seconds, and as a fraction of the frame interval when that is known), and
    the sample this frame added to the estimate (exposure s, weight, frame interval s) if any."""

    mode: str
    seconds: float
    fraction: float | None = None
    sample: tuple[float, float, float] | None = None
    estimate: ExposureEstimate | None = None  # the running estimate after this frame (estimated mode)
    speed: float | None = None  # the frame's point speed (px/s) since the previous tracked frame (estimated mode)
    completed_speed: float | None = None  # the previous raw frame's central speed (px/s), completed by this frame


@dataclasses.dataclass(frozen=True)
class FrameOutcome:
    """What one frame produced: its status, its poses when tracked (camera-to-world), a keyframe
    made at it, keyframe images replaced by deblurred ones, and the tracker's diagnostics."""

    index: int
    timestamp: float
    status: str  # "keyframe" (first frame), or the tracker's Status name in lower case
    T_world_mid: Pose | None = None
    T_world_start: Pose | None = None
    T_world_end: Pose | None = None
    new_keyframe: NewKeyframe | None = None
    replaced_images: tuple[tuple[float, np.ndarray], ...] = ()  # (stamp, deblurred image) of an earlier keyframe
    result: TrackResult | None = None
    fit: Fit | None = None  # the fit of a tracked (or implausible) frame
    exposure: ExposureReport | None = None
    seconds: float = 0.0  # the whole step
    track_seconds: float = 0.0  # tracking (and re-tracking after a pending deblur) only
    note: str = ""  # why a frame has no pose (monocular: not initialised yet, lost)
    earlier_keyframe: NewKeyframe | None = None  # a keyframe at an earlier frame made now (the monocular start's reference)
    points: object | None = None  # world points leaving the window (odometry.mono.PointCloud), for points.ply
    backend_seconds: float = 0.0  # the monocular back-end: candidates, bundle adjustment, marginalisation
    ba: object | None = None  # the bundle adjustment's report (mono.ba.BAReport) when one ran

    @property
    def tracked(self) -> bool:
        return self.T_world_mid is not None


@runtime_checkable
class Pipeline(Protocol):
    """A front-end (+ back-end) the sequence loop runs: one pure step per frame, its settings, and
    what a keyframe made without an exposure path waits for (``--resume`` restores it)."""

    config: RunConfig

    def step(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]: ...

    def pending_of(self, frame) -> PendingDeblur | None: ...
