"""The monocular pipeline's per-frame step: MBA-VO as the paper describes it.

Until initialised, frames go to the two-view initialiser (``mono.init``): corners tracked from a
reference frame until the parallax is enough; then the reference becomes the first keyframe with
the triangulated points, and the frame is tracked against it with the blur model. From then on the
front-end is the RGB-D pipeline's (``rgbd.RGBDPipeline``: blur-aware tracking, deblurred keyframes,
plausibility checks, estimated exposure) with depth taken from the window's points instead of a
sensor; each tracked frame refines the candidate points of the window's keyframes along their
epipolar lines (``mono.candidates``; blur-aware, the sharp keyframes' patterns are blurred along the
frame's tracked exposure path first), and each new keyframe runs the back-end: ready candidates join
the window, the windowed photometric bundle adjustment (``mono.ba``) refines poses, affine
brightness and inverse depths, and the oldest keyframe is marginalised when the window is full.
After ``reset_after_drops`` drops in a row the system initialises again. The new start keeps the
lost window's speed: the recent motion of median speed (``mono.motions``) carries the last good
pose over the gap to the new reference frame, and the two-view start is scaled so that the camera
moves at that speed. Besides the RGB-D pipeline's keyframe rules, DSO's point-shift rule
(``mono.keyframes``) asks for keyframes, and the frame statistics are over the keyframe points in
the frame's view (``odometry.inview``).
"""

from __future__ import annotations

import dataclasses
import time
import typing
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..config import MonoConfig
from ..deblur import exposure_blur_px
from ..geometry import ExposureTrajectory, Pose, interpolate
from ..image import delinearize, linearize, quantize16
from ..mono.ba import BAReport, bundle_adjust, marginalize
from ..mono.candidates import FrameBlur, activate, select_candidates, trace
from ..mono.depthmap import filled_depth, project_points, sparse_depth
from ..mono.direct_init import DirectInitializer
from ..mono.init import TwoView, TwoViewTracker
from ..mono.keyframes import wants_keyframe
from ..mono.motions import Motions, PoseAt
from ..mono.window import Window, add_keyframe, add_points, frame_affine, relative_affine, world_points
from ..tracking import Keyframe, Status, track
from .inview import ViewStats, in_view_stats
from .rgbd import RGBDPipeline
from .state import Fit, FrameOutcome, KeyframeState, NewKeyframe, Pairing, RunState

__all__ = ["MonoPipeline", "MonoState", "PointCloud"]

SAMPLING_KEYFRAMES = 3  # window keyframes before frames are sampled for the estimated exposure


@dataclasses.dataclass(frozen=True)
class PointCloud:
    """World points (N, 3) with their intensity (N,) in [0, 1] (display values)."""

    xyz: np.ndarray
    intensity: np.ndarray


@dataclasses.dataclass(frozen=True)
class MonoState:
    """The monocular system between frames: the initialiser while not initialised, else the
    window (keyframe slots oldest first, with their stamps) and each slot's candidate points."""

    initialiser: Any = None  # mono.init.TwoViewTracker or mono.direct_init.DirectInitializer while initialising
    reference: tuple[float, np.ndarray] | None = None  # (stamp, raw image) the initialiser started from
    tries: int = 0  # frames offered to the initialiser since its reference
    origin: Pose = dataclasses.field(default_factory=Pose.identity)  # the world pose the next initialisation starts at
    depth: float = 1.0  # the median depth of the next initialisation's points when no speed is known (the world's scale)
    motions: Motions = Motions()  # the recent frame-to-frame motions (kept over a restart)
    lost: PoseAt | None = None  # the last good pose before the loss the next start follows
    window: Window | None = None
    slots: tuple[int, ...] = ()  # occupied window slots, oldest first
    stamps: tuple[float, ...] = ()  # their keyframes' stamps
    candidates: tuple = ()  # per window slot: mono.candidates.Candidates or None
    initialisations: int = 0
    last_stamp: float | None = None  # the previous frame's stamp
    frame_dt: float = 0.0  # the interval between the last two frames (s)

    @property
    def initialised(self) -> bool:
        return self.window is not None

    def replace(self, **changes) -> "MonoState":
        return dataclasses.replace(self, **changes)

    def restart(self, origin: Pose, depth: float | None = None, lost: PoseAt | None = None) -> "MonoState":
        """Not initialised again, the next start at ``origin`` with its points' median depth ``depth``
        (None: as before) or, when motions are kept, following on from the last good pose ``lost``
        (None: as before); the frame clock, counts and motions kept."""
        return MonoState(origin=origin, depth=self.depth if depth is None else depth, motions=self.motions,
                         lost=self.lost if lost is None else lost, initialisations=self.initialisations,
                         last_stamp=self.last_stamp, frame_dt=self.frame_dt)

    def start_at(self, stamp: float) -> "MonoState":
        """The next start's reference frame is at ``stamp``: after a loss, its pose is the last good
        pose carried over the gap at the typical (median speed) recent motion."""
        typical = self.motions.typical()
        if self.lost is None or typical is None:
            return self
        return self.replace(origin=typical.carry(self.lost, stamp))

    def start_scale(self, two_view: TwoView, dt: float) -> float:
        """The factor a two-view start (median depth 1) is scaled by: after a loss, so that its
        translation over ``dt`` seconds is at the typical recent speed; else ``depth``."""
        typical = self.motions.typical()
        length = float(np.linalg.norm(np.asarray(two_view.T_ref_cur.t)))
        if self.lost is None or typical is None or not typical.speed > 0 or not length > 0 or not dt > 0:
            return self.depth
        return typical.speed * dt / length

    def moved(self, mids: tuple) -> "MonoState":
        """With the motion between the last two recent mid poses ``mids`` ((stamp, T_world_mid), ...) kept."""
        if len(mids) < 2:
            return self
        return self.replace(motions=self.motions.add(PoseAt(*mids[-2]), PoseAt(*mids[-1])))


@dataclasses.dataclass(frozen=True)
class MonoPipeline(RGBDPipeline):
    """Blur-aware monocular visual odometry: the blur-aware tracker over a windowed photometric
    bundle adjustment of deblurred keyframes (depth, when the sequence has it, is not used; keyframes
    are deblurred with ``mono.deblur_regularization``; the tracker recomputes its Jacobian as
    ``mono.fresh_jacobian_levels`` says)."""

    checkpoints: typing.ClassVar[bool] = True  # --resume: its window and points cannot be rebuilt from the run's records

    def __post_init__(self):
        mono = self.config.mono
        config = self.config.replace(tracker=dict(depth_weight=0.0, fresh_jacobian_levels=mono.fresh_jacobian_levels),
                                     deblur=dict(regularization=mono.deblur_regularization))
        object.__setattr__(self, "config", config)

    def probe_frames(self) -> int:
        """The most frames the exposure probe runs (``mono.exposure_probe``): the monocular loop,
        blind to blur and deblurring nothing, pairs frames only once its window holds
        ``SAMPLING_KEYFRAMES`` keyframes, and a pair needs two speeds far enough apart."""
        return self.config.mono.exposure_probe

    def step(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        t0 = time.perf_counter()
        frame = dataclasses.replace(frame, depth=None)
        mono = state.backend or MonoState(motions=Motions(keep=self.config.mono.restart_motions))
        if mono.last_stamp is not None and frame.timestamp > mono.last_stamp:
            mono = mono.replace(frame_dt=frame.timestamp - mono.last_stamp)
        state = state.replace(backend=mono.replace(last_stamp=frame.timestamp))
        mono = state.backend
        if not mono.initialised:
            state, outcome = self._initialise(state.replace(backend=mono), frame, index)
        else:
            state, outcome = self._track_mono(state, frame, index)
        if outcome.tracked and state.backend.initialised and state.mids[-1][0] == frame.timestamp:
            state = state.replace(backend=state.backend.moved(state.mids))
        return state, dataclasses.replace(outcome, seconds=time.perf_counter() - t0)

    # ------------------------------------------------------------------------ initialisation

    def _waiting(self, state: RunState, frame, index: int, note: str) -> tuple[RunState, FrameOutcome]:
        report = self.exposure_report(state, frame, 0.0)
        return state, FrameOutcome(index, frame.timestamp, "initialising", exposure=report, note=note)

    def start_initialiser(self, image):
        """The initialiser ``mono.initialiser`` names, its reference ``image``: corners (``mono.init``) or
        direct (``mono.direct_init``, comparing frames in linear radiance)."""
        cfg = self.config.mono
        if cfg.initialiser == "direct":
            return DirectInitializer.start(image, self.camera, cfg, gamma=self.config.tracker.response_gamma)
        return TwoViewTracker.start(image, self.camera, cfg)

    def _initialise(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        """Offer the frame to the two-view initialiser; start the system when it succeeds."""
        mono, cfg = state.backend, self.config.mono
        if mono.initialiser is None or mono.tries >= cfg.init_max_frames:
            again = f" (no initialisation in {mono.tries} frames: starting again)" if mono.initialiser is not None else ""
            mono = mono.replace(initialiser=self.start_initialiser(frame.image),
                                reference=(frame.timestamp, frame.image), tries=0).start_at(frame.timestamp)
            return self._waiting(state.replace(backend=mono), frame, index, "initialising: reference frame" + again)
        initialiser, two_view = mono.initialiser.update(frame.image)
        mono = mono.replace(initialiser=initialiser, tries=mono.tries + 1)
        if two_view.restart:  # too few corners left to ever succeed: this frame is the new reference
            mono = mono.replace(initialiser=self.start_initialiser(frame.image),
                                reference=(frame.timestamp, frame.image), tries=0).start_at(frame.timestamp)
        state = state.replace(backend=mono)
        if not two_view.ok:
            return self._waiting(state, frame, index, f"initialising: {two_view.reason}")
        return self._start(state, frame, index, two_view)

    def _first_image(self, state: RunState, two_view, path: ExposureTrajectory, rho: float) -> tuple[np.ndarray, bool]:
        """The reference frame as the first keyframe stores it, and whether it was deblurred: along
        its exposure ``path`` (about its middle; readout fraction ``rho``) when blurred enough."""
        cfg, raw = self.config, state.backend.reference[1]
        sparse = np.full(raw.shape, np.nan, np.float32)
        u, v = np.rint(two_view.pixels).astype(int).T
        sparse[v, u] = 1.0 / np.maximum(two_view.idepth, 1e-6)
        depth = filled_depth(sparse)
        if not (cfg.tracker.blur_aware and cfg.odometry.deblur_first_keyframe and not self.probe and np.isfinite(depth).all()
                and exposure_blur_px(depth, self.camera, path, readout=rho)[0] > cfg.odometry.deblur_min_blur_px):
            return quantize16(raw), False
        return self.deblurred(raw, depth, path, rho)[0], True

    def two_view_path(self, state: RunState, frame, two_view) -> tuple[ExposureTrajectory, float]:
        """(exposure path about its middle, readout fraction) of the reference and the current frame
        at the two-view motion's velocity, exposed for the estimated or known exposure time."""
        exposure = self.exposure_of(state, frame, state.backend.frame_dt)  # over the frame interval, not the reference's age
        return self.velocity_path(two_view.T_ref_cur, frame.timestamp - state.backend.reference[0], exposure)

    def frame_interval(self, state: RunState, frame) -> float:
        """The frame interval (s): between the last two frames received (tracked or not), else as the
        RGB-D pipeline has it (between the last two tracked frames)."""
        mono = state.backend
        return mono.frame_dt if mono is not None and mono.frame_dt > 0 else super().frame_interval(state, frame)

    def _start(self, state: RunState, frame, index: int, two_view) -> tuple[RunState, FrameOutcome]:
        """The reference frame (deblurred) as the first keyframe of a new window with the triangulated
        points and the candidates that converge in this frame, and this frame tracked against it
        (blur-aware) from the two-view pose."""
        mono, cfg = state.backend, self.config
        two_view = rescaled(two_view, mono.start_scale(two_view, frame.timestamp - mono.reference[0]))
        velocity, rho = self.two_view_path(state, frame, two_view)
        stamp, (image, sharp) = mono.reference[0], self._first_image(state, two_view, velocity, rho)
        window = Window.empty(cfg.mono.window, cfg.mono.points, self.camera.height, self.camera.width, recorded=self.ba.ba_blur_samples > 1)
        raw = self.recorded_frame(mono.reference[1]) if window.recorded else None
        window, slot = add_keyframe(window, linearize(image, cfg.tracker.response_gamma), mono.origin, raw=raw, exposure=velocity)
        window, _ = add_points(window, slot, two_view.pixels, two_view.idepth)
        candidates = [None] * cfg.mono.window
        candidates[slot] = select_candidates(linearize(image, cfg.tracker.response_gamma), cfg.mono.candidates, cfg.mono)
        mono = mono.replace(initialiser=None, reference=None, tries=0, window=window, slots=(slot,), stamps=(stamp,),
                            candidates=tuple(candidates), initialisations=mono.initialisations + 1)
        T_world_frame = mono.origin.compose(two_view.T_ref_cur)
        path = velocity.seen_from(T_world_frame) if sharp else None
        mono = self._activate(self.traced(mono, frame.image, T_world_frame, path=path, readout=rho), T_world_frame)
        state = state.replace(backend=mono)
        kf = KeyframeState(self.make_keyframe(state, image, None, mono.origin), mono.origin, stamp)
        state = state.replace(keyframe=kf, mids=((stamp, mono.origin),), keyframes=state.keyframes + 1, fits=(), pending=None,
                              consecutive_drops=0)
        new = NewKeyframe(stamp, mono.origin, image)
        guess = velocity.seen_from(two_view.T_ref_cur)  # the two-view pose, exposed at the two-view velocity
        result = track(kf.keyframe, frame.image, guess, self.tracker_config(frame, True), readout=rho)
        if not result.status.ok:
            mono = mono.restart(mono.origin)
            state = state.replace(backend=mono, keyframe=None, mids=state.mids[:0], pending=None)
            return self._waiting(state, frame, index, f"initialising: the two-view start did not track ({result.status.name.lower()})")
        frame = dataclasses.replace(frame, depth=self.frame_depth(state, result.trajectory.middle()))
        stats = self.frame_stats(state, result, None)
        state, outcome = self._tracked(state, frame, index, result, False, Fit(float(result.diagnostics["rms"]), None), stats)
        state = self._trace(state.replace(mids=self.one_frame_back(state, stamp)), frame, outcome)
        if outcome.new_keyframe is not None:
            state, outcome = self._backend(state, frame, outcome)
        note = f"initialised: parallax {two_view.parallax_deg:.1f} deg, {len(two_view.idepth)} points"
        return state, dataclasses.replace(outcome, earlier_keyframe=new, note=note)

    def one_frame_back(self, state: RunState, stamp: float) -> tuple:
        """The recent mid poses after the two-view start, (reference, current frame), with the
        reference moved along the motion to one frame interval before the current frame, so that the
        constant-velocity prediction spans one frame interval (its exposure is a fraction of it)."""
        (_, T_ref), (t_cur, T_cur) = state.mids[-2], state.mids[-1]
        dt = self.frame_interval(state, None)
        if not 0.0 < dt < t_cur - stamp:
            return state.mids
        s = 1.0 - dt / (t_cur - stamp)
        return ((t_cur - dt, interpolate(T_ref, T_cur, s)), (t_cur, T_cur))

    # ------------------------------------------------------------------------------ tracking

    def exposure_pairing(self, state: RunState, frame, T_w_mid: Pose, speed: float, dt: float) -> Pairing:
        """As the RGB-D pipeline's, but a frame joins the exposure estimate's pairs only once the
        window holds ``SAMPLING_KEYFRAMES`` keyframes: before, its depth (from the few points of the
        two-view start) is too coarse to measure blur with, and a wrong early sample pulls the estimate
        (a median of few samples) far off. The frame kept for pairing carries the depth of the
        window's points seen from its tracked pose (NaN elsewhere), not the filled map it was tracked
        with: a pair's tracking then uses the points only, where the depth is known, and its blur
        length (hence the sample) is not skewed by the filled map's guesses between points."""
        mono = state.backend
        if mono is None or len(mono.slots) < SAMPLING_KEYFRAMES:
            return Pairing(state.recent)
        frame = dataclasses.replace(frame, depth=self.window_depth(mono, T_w_mid))
        return super().exposure_pairing(state, frame, T_w_mid, speed, dt)

    def make_keyframe(self, state: RunState, image, depth, T_world_kf: Pose) -> Keyframe:
        """The tracker's keyframe: its image with the window's points seen from ``T_world_kf``."""
        x, z, ok = project_points(self.camera, T_world_kf.inverse(), self.window_xyz(state.backend))
        return Keyframe.from_points(image, x[ok], z[ok], self.camera, self.config.tracker)

    def window_xyz(self, mono: MonoState) -> np.ndarray:
        """The window's active points in the world frame (N, 3)."""
        xyz, _ = world_points(mono.window, self.camera)
        return np.asarray(xyz, np.float32)

    def window_depth(self, mono: MonoState, T_world_cam: Pose) -> np.ndarray:
        """Sparse depth of the window's points seen from ``T_world_cam`` (NaN where none)."""
        return sparse_depth(self.camera, T_world_cam, self.window_xyz(mono))

    def frame_depth(self, state: RunState, T_kf_mid: Pose) -> np.ndarray:
        """A filled depth map of the frame at ``T_kf_mid`` (in the current keyframe) from the window's points."""
        return filled_depth(self.window_depth(state.backend, state.keyframe.T_world_kf.compose(T_kf_mid)))

    def point_stats(self, keyframe: Keyframe, path: ExposureTrajectory, prev: Pose, predicted: Pose | None) -> ViewStats:
        """As the RGB-D pipeline's, but over the keyframe points in the frame's view at its mid pose
        (``odometry.inview``), with DSO's point shift."""
        return in_view_stats(keyframe, path, prev, predicted)

    def wants_keyframe(self, stats: ViewStats) -> bool:
        """The RGB-D pipeline's keyframe rules, or DSO's point-shift rule (``mono.keyframe_shift``)."""
        cam = self.camera
        return super().wants_keyframe(stats) or wants_keyframe(stats.shift, cam.width, cam.height, self.config.mono.keyframe_shift)

    def _track_mono(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        guess, _ = self.predict(state, frame)
        frame = dataclasses.replace(frame, depth=self.frame_depth(state, guess.middle()))
        state, outcome = self._track(state, frame, index)
        if outcome.replaced_images:  # the first keyframe deblurred: the window sees it too
            state = state.replace(backend=self._replace_images(state.backend, outcome.replaced_images))
        if outcome.tracked:
            state = self._trace(state, frame, outcome)
        if outcome.new_keyframe is not None and state.backend.initialised:
            state, outcome = self._backend(state, frame, outcome)
        return state, outcome

    def _dropped(self, state: RunState, frame, index: int, result) -> tuple[RunState, FrameOutcome]:
        """A drop as in the RGB-D pipeline, but after ``reset_after_drops`` drops in a row the system
        initialises again, following on from the last good pose at the recent speed
        (``MonoState.start_at``, ``start_scale``; with no motions kept, at the last good pose and the
        lost window's median depth seen from it)."""
        odo = self.config.odometry
        odd = result is not None and result.status == Status.IMPLAUSIBLE
        state = state.replace(dropped=state.dropped + 1, consecutive_drops=state.consecutive_drops + 1,
                              mids=state.mids if odd else state.mids[-1:])
        note = ""
        if state.consecutive_drops >= odo.reset_after_drops:
            origin = state.mids[-1][1]
            depth = self.window_depth(state.backend, origin)
            depth = float(np.median(depth[np.isfinite(depth)])) if np.isfinite(depth).any() else None  # the next start keeps the scale
            state = state.replace(backend=state.backend.restart(origin, depth, PoseAt(state.mids[-1][0], origin)),
                                  keyframe=None, pending=None, consecutive_drops=0, fits=())
            note = f"lost after {odo.reset_after_drops} drops: initialising again"
        status = (result.status if result is not None else Status.TOO_FEW_POINTS).name.lower()
        report = self.exposure_report(state, frame, 0.0)
        return state, FrameOutcome(index, frame.timestamp, status, result=result, exposure=report, note=note)

    # ------------------------------------------------------------------------------- back-end

    def _trace(self, state: RunState, frame, outcome: FrameOutcome) -> RunState:
        """Each window keyframe's candidates searched along their epipolar lines in this frame."""
        diagnostics = outcome.result.diagnostics if outcome.result is not None else {}
        path = None
        if self.config.tracker.blur_aware and outcome.T_world_start is not None:  # sharp keyframes, a blurry frame
            path = ExposureTrajectory(outcome.T_world_start, outcome.T_world_end)
        return state.replace(backend=self.traced(state.backend, frame.image, outcome.T_world_mid, diagnostics.get("affine", [0.0, 0.0]),
                                                 path, float(diagnostics.get("readout", 0.0))))

    def traced(self, mono: MonoState, image, T_world_frame: Pose, affine=(0.0, 0.0), path: ExposureTrajectory | None = None,
               readout: float = 0.0) -> MonoState:
        """``mono`` with each window keyframe's candidates searched along their epipolar lines in
        ``image`` (display values) seen from ``T_world_frame``. ``affine``: the tracker's (a, b) of the
        frame against its reference, the window's newest keyframe; each keyframe's candidates are
        matched under the frame's brightness relative to that keyframe (``mono.window.frame_affine``,
        ``relative_affine``). ``path``: the frame's exposure path (``T_world_*``, readout fraction
        ``readout``) when the keyframes are sharp and the frame is blurry: the keyframes' patterns
        are blurred along it before they are searched for."""
        image = linearize(image, self.config.tracker.response_gamma)
        T_frame_world = T_world_frame.inverse()
        frame_ab = frame_affine(mono.window.affine[mono.slots[-1]], jnp.asarray(affine, mono.window.affine.dtype))
        cands = list(mono.candidates)
        for slot in mono.slots:
            if cands[slot] is None:
                continue
            T_world_host = _slot_pose(mono.window, slot)
            blur = None if path is None else FrameBlur.create(path.seen_from(T_world_host.inverse()), readout,
                                                              typical_idepth(mono.window, slot))
            cands[slot] = trace(cands[slot], mono.window.images[slot], image, self.camera, T_frame_world.compose(T_world_host),
                                relative_affine(frame_ab, mono.window.affine[slot]), self.config.mono, blur)
        return mono.replace(candidates=tuple(cands))

    def _replace_images(self, mono: MonoState, images) -> MonoState:
        """The window's keyframe images replaced by (stamp, image) pairs (deblurred later)."""
        window = mono.window
        for stamp, image in images:
            slot = next((sl for sl, t in zip(mono.slots, mono.stamps) if abs(t - stamp) < 1e-9), None)
            if slot is not None:
                linear = jnp.asarray(linearize(image, self.config.tracker.response_gamma), window.images.dtype)
                window = eqx.tree_at(lambda w: w.images, window, window.images.at[slot].set(linear))
        return mono.replace(window=window)

    def _activate(self, mono: MonoState, T_world_frame: Pose) -> MonoState:
        """Ready candidates of every window keyframe join the window's points (as many as fit), those
        with enough parallax between their host and the latest frame traced (``T_world_frame``)."""
        window, cands = mono.window, list(mono.candidates)
        for slot in reversed(mono.slots):  # the newest keyframes' points first
            c = cands[slot]
            if c is not None:
                window, cands[slot] = activate(window, jnp.asarray(slot, jnp.int32), c, self.config.mono, self.camera, T_world_frame)
        return mono.replace(window=window, candidates=tuple(cands))

    def _backend(self, state: RunState, frame, outcome: FrameOutcome) -> tuple[RunState, FrameOutcome]:
        """A new keyframe joins the window (the oldest marginalised first when it is full) with the
        affine brightness its tracking found against the newest keyframe (``mono.window.frame_affine``),
        ready candidates become points, the window is bundle-adjusted, and the tracker's keyframe and
        the recent poses follow the adjusted poses."""
        t0 = time.perf_counter()
        mono, cfg, new = state.backend, self.config, outcome.new_keyframe
        tracked = outcome.result.diagnostics.get("affine", (0.0, 0.0)) if outcome.result is not None else (0.0, 0.0)
        affine = frame_affine(mono.window.affine[mono.slots[-1]], jnp.asarray(tracked, mono.window.affine.dtype))
        cloud = None
        if len(mono.slots) >= cfg.mono.window:
            mono, cloud = self._marginalize_oldest(mono)
        image = linearize(new.image, cfg.tracker.response_gamma)
        raw = self.recorded_frame(frame.image) if mono.window.recorded else None
        window, slot = add_keyframe(mono.window, image, new.T_world_kf, affine, raw, self.keyframe_exposure(outcome, new.T_world_kf))
        cands = list(mono.candidates)
        cands[slot] = select_candidates(image, cfg.mono.candidates, cfg.mono)
        mono = self._activate(mono.replace(window=window, slots=(*mono.slots, slot), stamps=(*mono.stamps, new.stamp),
                                           candidates=tuple(cands)), new.T_world_kf)
        window, report, note = self._adjusted(mono.window, slot, outcome.note)
        mono = mono.replace(window=window)
        T_new = _slot_pose(window, slot)
        correction = T_new.compose(new.T_world_kf.inverse())
        state = state.replace(backend=mono)
        kf = KeyframeState(self.make_keyframe(state, new.image, None, T_new), T_new, new.stamp)
        mids = tuple((t, correction.compose(T)) for t, T in state.mids)
        state = state.replace(keyframe=kf, mids=mids)
        outcome = dataclasses.replace(outcome, points=cloud, backend_seconds=time.perf_counter() - t0, ba=report, note=note)
        return state, outcome

    def recorded_frame(self, image) -> np.ndarray:
        """A keyframe's recorded frame (display values) as a window that keeps them stores it."""
        return linearize(quantize16(image), self.config.tracker.response_gamma)

    def keyframe_exposure(self, outcome: FrameOutcome, T_world_kf: Pose) -> ExposureTrajectory | None:
        """A new keyframe's exposure path about its pose ``T_world_kf`` (None where the frame has none)."""
        if outcome.T_world_start is None or outcome.T_world_end is None:
            return None
        T_kf_world = T_world_kf.inverse()
        return ExposureTrajectory(T_kf_world.compose(outcome.T_world_start), T_kf_world.compose(outcome.T_world_end))

    @property
    def ba(self) -> MonoConfig:
        """The back-end's settings: ``config.mono`` with the adjustment's blur model off
        (``ba_blur_samples`` = 1) when the tracker is blind to blur."""
        mono = self.config.mono
        return mono if self.config.tracker.blur_aware else dataclasses.replace(mono, ba_blur_samples=1)

    def _adjusted(self, window: Window, slot: int, note: str) -> tuple[Window, BAReport, str]:
        """(window, report, note): ``window`` bundle-adjusted. When the adjustment turns the new
        keyframe ``slot``'s view of the points by more than ``mono.ba_max_move`` of the width (its
        pose fitted to newly activated points that the adjustment then drops as outliers), it is
        run again from the start without those points; when that one jumps too, the window is left
        unadjusted (without them)."""
        cfg, limit = self.ba, self.config.mono.ba_max_move * self.camera.width
        adjusted, report = bundle_adjust(window, self.camera, cfg)
        moved = view_moved_px(self.camera, window, adjusted, slot)
        if moved <= limit:
            return adjusted, report, note
        kept = eqx.tree_at(lambda w: w.point_valid, window, window.point_valid & adjusted.point_valid)
        again, report = bundle_adjust(kept, self.camera, cfg)
        retried = view_moved_px(self.camera, kept, again, slot)
        what = "adjusted again without its dropped points" if retried <= limit else f"undone (again {retried:.0f} px)"
        note = (note + "; " if note else "") + f"bundle adjustment {what}: the new keyframe's view moved {moved:.0f} px"
        return (again if retried <= limit else kept), report, note

    def _marginalize_oldest(self, mono: MonoState) -> tuple[MonoState, PointCloud]:
        """The oldest keyframe leaves the window: its points are returned (for points.ply) and its
        information stays as a prior on the others."""
        slot = mono.slots[0]
        cloud = self.slot_points(mono, slot)
        window = marginalize(mono.window, slot, self.camera, self.ba)
        cands = list(mono.candidates)
        cands[slot] = None
        return mono.replace(window=window, slots=mono.slots[1:], stamps=mono.stamps[1:], candidates=tuple(cands)), cloud

    def slot_points(self, mono: MonoState, slot: int | None = None) -> PointCloud:
        """The world points hosted by ``slot`` (None: every point of the window) and their intensity."""
        window = mono.window
        if slot is not None:
            window = eqx.tree_at(lambda w: w.point_valid, window, window.point_valid & (window.host == slot))
        xyz, intensity = world_points(window, self.camera)
        display = delinearize(np.clip(np.asarray(intensity, np.float32), 0.0, None), self.config.tracker.response_gamma)
        return PointCloud(np.asarray(xyz, np.float32), np.asarray(display, np.float32))

    def final_points(self, state: RunState) -> PointCloud | None:
        """The points still in the window at the end of a run (points.ply gets them last)."""
        mono = state.backend
        return self.slot_points(mono) if mono is not None and mono.initialised else None


def rescaled(two_view: TwoView, scale: float) -> TwoView:
    """A two-view start (median point depth 1) scaled by ``scale``: its translation and point depths
    (the median depth becomes ``scale``; the bearings and rotation are unchanged)."""
    if scale == 1.0:
        return two_view
    T = two_view.T_ref_cur
    return dataclasses.replace(two_view, T_ref_cur=Pose(T.q, T.t * scale), idepth=(two_view.idepth / scale).astype(np.float32))


def view_moved_px(camera, before: Window, after: Window, slot: int) -> float:
    """The median distance (pixels) between where keyframe ``slot`` sees the window's points (as
    ``after`` has them) from its pose in ``before`` and from its pose in ``after``; 0 when none is in
    view of both."""
    xyz, _ = world_points(after, camera)
    xyz = np.asarray(xyz, np.float32)
    if not len(xyz):
        return 0.0
    x0, _, ok0 = project_points(camera, _slot_pose(before, slot).inverse(), xyz)
    x1, _, ok1 = project_points(camera, _slot_pose(after, slot).inverse(), xyz)
    both = ok0 & ok1
    return float(np.median(np.linalg.norm(x1[both] - x0[both], axis=1))) if both.any() else 0.0


def typical_idepth(window: Window, slot: int) -> float:
    """The median inverse depth of the window's points hosted by ``slot`` (of all its points when it
    hosts none; 0 when there are none)."""
    valid, idepth = np.asarray(window.point_valid), np.asarray(window.idepth)
    own = valid & (np.asarray(window.host) == slot)
    use = own if own.any() else valid
    return float(np.median(idepth[use])) if use.any() else 0.0


def _slot_pose(window: Window, slot: int) -> Pose:
    return Pose(window.poses.q[slot], window.poses.t[slot])
