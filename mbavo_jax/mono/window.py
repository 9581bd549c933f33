"""The sliding window of the monocular back-end (DSO's): K keyframe slots and P point slots of fixed
shape, padded and masked, so that one sequence compiles the bundle adjustment once.

Each keyframe slot holds a sharp (deblurred) keyframe image in linear radiance, the frame as it was
recorded (``raw``, blurry) with its exposure path about the keyframe's pose, its pose ``T_world_kf``
(camera-to-world) and its affine brightness (a, b): a pixel of host h seen in target t predicts
``I_t ≈ e^(a_t - a_h) (I_h - b_h) + b_t``. Each point slot holds a host slot, its host pixel
(level 0) and its inverse depth. ``prior`` is the marginalisation prior on the keyframe variables.

The helpers below (``add_keyframe``, ``add_points``, ...) run on the host, outside ``jit``;
``insert_points`` is their compiled core for points (fixed shapes, no host round-trip).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..errors import ArgumentError
from ..geometry import quaternion as quat
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory
from ..image import bilinear

__all__ = ["Prior", "Window", "VARS", "add_keyframe", "add_points", "insert_points", "world_points", "points_of",
           "pose_delta", "set_slot_pose", "padded_length", "pad_rows", "frame_affine", "relative_affine"]

VARS = 8  # variables per keyframe: pose increment [Δr (3), Δt (3)] (``Pose.plus``), affine [Δa, Δb]


def pose_delta(pose: Pose, pose0: Pose) -> Float[Array, "6"]:
    """The increment from ``pose0`` to ``pose`` consistent with ``Pose.plus``: [log(q0⁻¹ q), t - t0]."""
    dq = quat.log(quat.product(quat.inverse(pose0.q), pose.q))
    return jnp.concatenate([dq, pose.t - pose0.t])


def _identity_poses(k: int, dtype) -> Pose:
    return Pose(jnp.tile(quat.identity(dtype), (k, 1)), jnp.zeros((k, 3), dtype))


class Prior(eqx.Module):
    """The marginalisation prior: ``E(δ) = ½ δᵀ H δ + bᵀ δ`` on the keyframe-variable increments δ
    (K x 8, flattened slot-major) relative to the linearisation point (``poses``, ``affine``), with the
    pose part of δ given by :func:`pose_delta`. Slots without prior information have zero rows
    (and an identity linearisation pose); ``H = 0`` means no prior."""

    H: Float[Array, "M M"]
    b: Float[Array, "M"]
    poses: Pose  # (K,) T_world_kf at the linearisation point
    affine: Float[Array, "K 2"]

    @staticmethod
    def zeros(k: int, dtype=jnp.float32) -> "Prior":
        m = VARS * k
        return Prior(jnp.zeros((m, m), dtype), jnp.zeros(m, dtype), _identity_poses(k, dtype), jnp.zeros((k, 2), dtype))

    def active(self) -> Bool[Array, ""]:
        """True when the prior holds any information."""
        return jnp.any(self.H != 0)

    def delta(self, poses: Pose, affine: Float[Array, "K 2"]) -> Float[Array, "M"]:
        """δ of the keyframe variables (poses, affine) from the linearisation point, flattened (8K,)."""
        dp = jax.vmap(pose_delta)(poses, self.poses)
        return jnp.concatenate([dp, affine - self.affine], axis=1).reshape(-1)


class Window(eqx.Module):
    """K keyframe slots and P point slots (fixed shapes; invalid slots are padding).

    ``stamp`` orders the keyframes by insertion (the oldest valid keyframe has the smallest stamp),
    since freed slots are reused.
    """

    images: Float[Array, "K H W"]  # keyframe images (sharp), linear radiance
    raw: Float[Array, "K h w"]  # the keyframes' frames as recorded (blurry), linear radiance; (K, 0, 0): none kept
    exposure: ExposureTrajectory  # (K,) each keyframe's exposure path T_kf_start, T_kf_end (identity: sharp)
    poses: Pose  # (K,) T_world_kf
    affine: Float[Array, "K 2"]  # (a, b) per keyframe
    kf_valid: Bool[Array, "K"]
    stamp: Int[Array, "K"]
    host: Int[Array, "P"]  # host slot of each point
    pixels: Float[Array, "P 2"]  # host pixel (col, row), level 0
    idepth: Float[Array, "P"]  # inverse z-depth in the host
    point_valid: Bool[Array, "P"]
    prior: Prior

    @staticmethod
    def empty(k: int, p: int, height: int, width: int, dtype=jnp.float32, recorded: bool = False) -> "Window":
        """A window with K free keyframe slots and P free point slots for height x width images;
        ``recorded``: it also keeps each keyframe's recorded frame (the blur-aware adjustment reads it)."""
        return Window(
            images=jnp.zeros((k, height, width), dtype),
            raw=jnp.zeros((k, height, width) if recorded else (k, 0, 0), dtype),
            exposure=ExposureTrajectory(_identity_poses(k, dtype), _identity_poses(k, dtype)),
            poses=_identity_poses(k, dtype),
            affine=jnp.zeros((k, 2), dtype),
            kf_valid=jnp.zeros(k, bool),
            stamp=jnp.zeros(k, jnp.int32),
            host=jnp.zeros(p, jnp.int32),
            pixels=jnp.zeros((p, 2), dtype),
            idepth=jnp.ones(p, dtype),
            point_valid=jnp.zeros(p, bool),
            prior=Prior.zeros(k, dtype),
        )

    @property
    def slots(self) -> int:
        return self.images.shape[0]

    @property
    def capacity(self) -> int:
        return self.idepth.shape[0]

    @property
    def recorded(self) -> bool:
        """Whether the window keeps its keyframes' recorded frames (``raw``)."""
        return self.raw.shape[1:] == self.images.shape[1:]


def frame_affine(reference: Float[Array, "2"], tracked: Float[Array, "2"]) -> Float[Array, "2"]:
    """The window's affine brightness (a_f, b_f) of a frame that the tracker fitted as e^a · I_ref + b
    (``tracked`` = (a, b)) against the keyframe whose window affine is ``reference`` = (a_r, b_r):
    since I_ref ≈ e^(a_r − a_h) (I_h − b_h) + b_r for every keyframe h, the frame is
    e^(a_f − a_h) (I_h − b_h) + b_f with a_f = a_r + a and b_f = b + e^a b_r."""
    return jnp.stack([reference[0] + tracked[0], tracked[1] + jnp.exp(tracked[0]) * reference[1]])


def relative_affine(target: Float[Array, "2"], host: Float[Array, "2"]) -> Float[Array, "2"]:
    """(a, b) with I_target ≈ e^a · I_host + b for window affines ``target`` and ``host``:
    a = a_t − a_h, b = b_t − e^a b_h (the bundle adjustment's model, module text)."""
    a = target[0] - host[0]
    return jnp.stack([a, target[1] - jnp.exp(a) * host[1]])


def set_slot_pose(poses: Pose, slot, pose: Pose) -> Pose:
    """``poses`` with entry ``slot`` replaced by ``pose``."""
    return Pose(poses.q.at[slot].set(pose.q.astype(poses.q.dtype)), poses.t.at[slot].set(pose.t.astype(poses.t.dtype)))


def add_keyframe(window: Window, image, T_world_kf: Pose, affine=(0.0, 0.0), raw=None,
                 exposure: ExposureTrajectory | None = None) -> tuple[Window, int]:
    """``window`` with a new keyframe in its first free slot, and that slot. ``image``: (H, W) linear
    radiance (a deblurred keyframe); ``raw``: the frame as recorded (None: ``image``; kept only by a
    ``recorded`` window) and ``exposure`` its exposure path about ``T_world_kf`` (None: sharp).
    Raises ArgumentError when the window is full, a size differs, or ``raw`` has nowhere to go."""
    valid = np.asarray(window.kf_valid)
    free = np.flatnonzero(~valid)
    if free.size == 0:
        raise ArgumentError(f"the window is full ({valid.size} keyframes): marginalise one first")
    if raw is not None and not window.recorded:
        raise ArgumentError("this window keeps no recorded frames: make it with Window.empty(..., recorded=True)")
    image = np.asarray(image, np.float32)
    raw = image if raw is None else np.asarray(raw, np.float32)
    for a in (image, raw):
        if a.shape != tuple(window.images.shape[1:]):
            raise ArgumentError(f"keyframe image is {a.shape[1]}x{a.shape[0]}, the window holds "
                                f"{window.images.shape[2]}x{window.images.shape[1]} images")
    slot = int(free[0])
    dtype = window.images.dtype
    identity = Pose.identity(dtype)
    exposure = ExposureTrajectory(identity, identity) if exposure is None else exposure
    stamp = int(np.asarray(window.stamp).max()) + 1 if valid.any() else 0
    window = dataclasses.replace(
        window,
        images=window.images.at[slot].set(jnp.asarray(image, dtype)),
        raw=window.raw.at[slot].set(jnp.asarray(raw, dtype)) if window.recorded else window.raw,
        exposure=ExposureTrajectory(set_slot_pose(window.exposure.start, slot, exposure.start),
                                    set_slot_pose(window.exposure.end, slot, exposure.end)),
        poses=set_slot_pose(window.poses, slot, T_world_kf),
        affine=window.affine.at[slot].set(jnp.asarray(affine, dtype)),
        kf_valid=window.kf_valid.at[slot].set(True),
        stamp=window.stamp.at[slot].set(stamp),
        point_valid=window.point_valid & (window.host != slot),
    )
    return window, slot


def padded_length(n: int, least: int = 256) -> int:
    """The padded length of ``n`` rows: the next power of two, at least ``least`` (so that arrays
    whose length varies from call to call compile a few programs, not one per length)."""
    return max(least, 1 << max(int(n) - 1, 0).bit_length())


def pad_rows(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with zero rows appended up to ``n`` rows."""
    return np.concatenate([a, np.zeros((n - a.shape[0], *a.shape[1:]), a.dtype)]) if n > a.shape[0] else a


@jax.jit
def insert_points(window: Window, slot: Int[Array, ""], pixels: Float[Array, "N 2"], idepth: Float[Array, " N"],
                  mask: Bool[Array, " N"]) -> tuple[Window, Bool[Array, " N"]]:
    """``window`` with the points where ``mask`` (host pixels, inverse depths) hosted by keyframe
    ``slot``, in order, in its free point slots (lowest first), and which of them were added (all
    unless the free slots run out). One program per N and window shape."""
    p = window.capacity
    free = jnp.nonzero(~window.point_valid, size=p, fill_value=p)[0].astype(jnp.int32)
    rank = jnp.cumsum(mask, dtype=jnp.int32) - 1
    added = mask & (rank < jnp.sum(~window.point_valid, dtype=jnp.int32))
    dest = jnp.where(added, free[jnp.clip(rank, 0, p - 1)], jnp.int32(p))  # p: out of range, dropped
    put = lambda a, v: a.at[dest].set(v.astype(a.dtype), mode="drop")  # noqa: E731
    window = dataclasses.replace(window, host=put(window.host, jnp.broadcast_to(slot, dest.shape)), pixels=put(window.pixels, pixels),
                                 idepth=put(window.idepth, idepth), point_valid=put(window.point_valid, jnp.ones_like(mask)))
    return window, added


def add_points(window: Window, slot: int, pixels, idepth) -> tuple[Window, int]:
    """``window`` with points hosted by keyframe ``slot`` in its free point slots (in order), and how
    many were added (fewer than given when the window runs out of slots). ``pixels``: (N, 2) host
    pixels (col, row) at level 0; ``idepth``: (N,) inverse depths."""
    if not bool(np.asarray(window.kf_valid)[slot]):
        raise ArgumentError(f"keyframe slot {slot} is empty: add the keyframe before its points")
    pixels = np.asarray(pixels, np.float32).reshape(-1, 2)
    idepth = np.asarray(idepth, np.float32).reshape(-1)
    if pixels.shape[0] != idepth.shape[0]:
        raise ArgumentError(f"{pixels.shape[0]} pixels but {idepth.shape[0]} inverse depths")
    n = padded_length(pixels.shape[0])
    mask = np.arange(n) < pixels.shape[0]
    window, added = insert_points(window, jnp.asarray(slot, jnp.int32), pad_rows(pixels, n), pad_rows(idepth, n), mask)
    return window, int(np.asarray(added).sum())


def _world_point(images, poses: Pose, camera: PinholeCamera, host, pixel, idepth):
    """One point in world coordinates and its host intensity."""
    T = Pose(poses.q[host], poses.t[host])
    xyz = T.apply(camera.backproject(pixel, 1.0 / idepth))
    value, _ = bilinear(images[host], pixel)
    return xyz, value


@jax.jit
def _all_world_points(window: Window, camera: PinholeCamera):
    """Every point slot in world coordinates and its host intensity (one program per window shape)."""
    return jax.vmap(lambda h, x, d: _world_point(window.images, window.poses, camera, h, x, d))(window.host, window.pixels, window.idepth)


def world_points(window: Window, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """The valid points with a positive inverse depth: world coordinates (N, 3) and host intensity (N,)."""
    keep = np.flatnonzero(np.asarray(window.point_valid) & (np.asarray(window.idepth) > 0))
    if keep.size == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    xyz, value = jax.device_get(_all_world_points(window, camera))
    return np.asarray(xyz)[keep], np.asarray(value)[keep]


def points_of(window: Window, slot: int) -> tuple[np.ndarray, np.ndarray]:
    """The valid points hosted by keyframe ``slot``: pixels (N, 2) and z-depths (N,) (for the tracker)."""
    keep = np.asarray(window.point_valid) & (np.asarray(window.host) == slot) & (np.asarray(window.idepth) > 0)
    return np.asarray(window.pixels)[keep], 1.0 / np.asarray(window.idepth)[keep]
