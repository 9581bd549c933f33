"""A ray-cast scene of textured axis-aligned boxes: a room seen from inside plus boxes in it.

Rendering returns linear radiance and z-depth for a camera pose ``T_world_cam``; it is jit-compiled
and renders many sub-frame poses in one call (``render_exposure``), averaging radiance over the
exposure before the camera response is applied.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..image import bilinear_wrapped

__all__ = ["Scene", "make_textures", "default_scene", "scene_arrays", "render_exposure"]

TEXTURE_SIZE = 512


@dataclasses.dataclass(frozen=True)
class Scene:
    """Boxes (K, 2, 3) [min, max] in world metres; ``inside[k]`` renders box k from inside (the
    room); ``texture[k]`` indexes ``textures`` (T, S, S) of linear radiance; ``texels_per_m[k]``."""

    boxes: np.ndarray
    inside: np.ndarray
    texture: np.ndarray
    texels_per_m: np.ndarray
    textures: np.ndarray
    texture_names: tuple[str, ...]


def _value_noise(rng, size, octaves=5, base=4):
    img = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = base * 2**o
        grid = rng.uniform(size=(n + 1, n + 1)).astype(np.float32)
        grid[-1, :], grid[:, -1] = grid[0, :], grid[:, 0]  # tileable
        up = cv2.resize(grid, (size + size // n, size + size // n), interpolation=cv2.INTER_CUBIC)[:size, :size]
        img += amp * up
        total += amp
        amp *= 0.6
    img /= total
    return img


def _normalise(img):
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)


def _procedural(rng, kind, size):
    if kind == "noise":
        return _normalise(_value_noise(rng, size))
    if kind == "tiles":
        k = 8
        cells = rng.uniform(0.2, 0.9, size=(k, k)).astype(np.float32)
        img = cv2.resize(cells, (size, size), interpolation=cv2.INTER_NEAREST)
        img[:: size // k, :] = 0.05
        img[:, :: size // k] = 0.05
        return _normalise(0.75 * img + 0.25 * _value_noise(rng, size, octaves=4, base=8))
    if kind == "blobs":
        img = np.zeros((size, size), np.float32)
        for _ in range(60):
            c = rng.integers(0, size, 2)
            r = int(rng.integers(size // 40, size // 10))
            cv2.circle(img, (int(c[0]), int(c[1])), r, float(rng.uniform(0.2, 1.0)), -1)
        return _normalise(0.8 * cv2.GaussianBlur(img, (0, 0), 1.5) + 0.2 * _value_noise(rng, size))
    raise ValueError(kind)


def _real_images(shared_data: pathlib.Path | None):
    """A few real photos from ../shared/data, if present (textures from real images)."""
    out = []
    if shared_data is None or not shared_data.is_dir():
        return out
    for sub in ("tum_fr1_xyz_head37/rgb", "kitti07_head160/rgb"):
        d = shared_data / sub
        if d.is_dir():
            files = sorted(d.iterdir())
            if files:
                img = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
                if img is not None:
                    out.append((f"real:{sub.split('/')[0]}", img))
    return out


def make_textures(seed: int, size: int = TEXTURE_SIZE, use_real: bool = True, shared_data=None):
    """Textures as display intensities in [0, 1]: procedural noise, tiles and blobs, plus crops of
    real images from ``shared_data`` when ``use_real`` and the folder exists."""
    rng = np.random.default_rng(seed)
    names, texs = [], []
    for kind in ("noise", "tiles", "blobs", "noise", "blobs", "tiles"):
        names.append(kind)
        texs.append(_procedural(rng, kind, size))
    if use_real:
        if shared_data is None:
            env = os.environ.get("MBAVO_SHARED_DATA")
            shared_data = pathlib.Path(env) if env else pathlib.Path.cwd().parent / "shared" / "data"
        for name, img in _real_images(pathlib.Path(shared_data)):
            h, w = img.shape
            s = min(h, w)
            crop = img[(h - s) // 2 : (h - s) // 2 + s, (w - s) // 2 : (w - s) // 2 + s]
            crop = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
            names.append(name)
            texs.append(_normalise(crop))
    return np.stack(texs), tuple(names)


def default_scene(seed: int = 0, use_real_textures: bool = True, shared_data=None) -> Scene:
    """A 8 m x 5 m x 9 m room (camera near the origin looking along +z) with four boxes at
    depths 2-5 m."""
    textures, names = make_textures(seed, use_real=use_real_textures, shared_data=shared_data)
    rng = np.random.default_rng(seed + 1)
    boxes = [np.array([[-4.0, -2.5, -2.0], [4.0, 2.5, 7.0]])]
    for cx, cz, sz in ((-1.3, 2.6, 0.5), (1.2, 3.3, 0.6), (0.1, 4.8, 0.9), (-2.2, 5.2, 0.7)):
        cy = rng.uniform(-0.6, 0.8)
        boxes.append(np.array([[cx - sz, cy - sz, cz - sz], [cx + sz, cy + sz, cz + sz]]))
    k = len(boxes)
    texture = np.array([i % len(names) for i in range(k)])
    if len(names) > 6:  # put a real photo on the back wall region (room) and one box
        texture[0] = 6
        texture[2] = len(names) - 1
    return Scene(
        boxes=np.stack(boxes).astype(np.float32),
        inside=np.array([True] + [False] * (k - 1)),
        texture=texture.astype(np.int32),
        texels_per_m=np.array([110.0] + [220.0] * (k - 1), np.float32),
        textures=textures.astype(np.float32),
        texture_names=names,
    )


def scene_arrays(scene: Scene):
    """The scene as device arrays (boxes, inside, texture index, texels per metre, textures)."""
    return (
        jnp.asarray(scene.boxes),
        jnp.asarray(scene.inside),
        jnp.asarray(scene.texture),
        jnp.asarray(scene.texels_per_m),
        jnp.asarray(scene.textures),
    )


def _render_core(arrays, camera: PinholeCamera, T_world_cam: Pose, gamma):
    boxes, inside, tex_idx, tpm, textures = arrays
    h, w = camera.height, camera.width
    u, v = jnp.meshgrid(jnp.arange(w, dtype=jnp.float32), jnp.arange(h, dtype=jnp.float32))
    d_cam = jnp.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, jnp.ones_like(u)], -1)
    R = T_world_cam.rotation()
    d = d_cam @ R.T  # (h, w, 3); camera z of the hit equals the ray parameter t
    o = T_world_cam.t
    d_safe = jnp.where(jnp.abs(d) < 1e-9, 1e-9, d)
    inv = 1.0 / d_safe

    def hit_box(box, is_inside):
        t1 = (box[0] - o) * inv
        t2 = (box[1] - o) * inv
        tnear = jnp.minimum(t1, t2)
        tfar = jnp.maximum(t1, t2)
        t_enter = jnp.max(tnear, -1)
        t_exit = jnp.min(tfar, -1)
        ax_enter = jnp.argmax(tnear, -1)
        ax_exit = jnp.argmin(tfar, -1)
        eps = 1e-4
        t = jnp.where(is_inside, t_exit, t_enter)
        ok = (t_exit >= jnp.maximum(t_enter, eps)) & (t > eps)
        return jnp.where(ok, t, jnp.inf), jnp.where(is_inside, ax_exit, ax_enter)

    ts, axes = jax.vmap(hit_box)(boxes, inside)  # (K, h, w)
    k = jnp.argmin(ts, 0)
    t = jnp.min(ts, 0)
    axis = jnp.take_along_axis(axes, k[None], 0)[0]
    p = o + t[..., None] * d
    # texture coordinates: the two coordinates in the face plane, offset per face to break repeats
    coords = jnp.stack(
        [jnp.stack([p[..., 2], p[..., 1]], -1), jnp.stack([p[..., 0], p[..., 2]], -1), jnp.stack([p[..., 0], p[..., 1]], -1)]
    )  # (3, h, w, 2)
    c = jnp.take_along_axis(coords, axis[None, ..., None], 0)[0]
    scale = tpm[k]
    offset = (axis.astype(jnp.float32) * 97.0 + k.astype(jnp.float32) * 53.0)[..., None]
    uv = c * scale[..., None] + offset
    flat_tex = textures.reshape(textures.shape[0], -1)
    s = textures.shape[1]

    def sample(ti, uu, vv):
        return bilinear_wrapped(flat_tex[ti].reshape(s, s), uu, vv)

    display = jax.vmap(sample)(tex_idx[k].ravel(), uv[..., 0].ravel(), uv[..., 1].ravel()).reshape(h, w)
    radiance = jnp.clip(display, 0.0, 1.0) ** gamma  # textures are display values; radiance is linear
    depth = jnp.where(jnp.isfinite(t), t, 0.0)
    return radiance, depth


@jax.jit
def render_exposure(arrays, camera: PinholeCamera, poses: Pose, mid: Pose, gamma=2.2):
    """Mean linear radiance over the sub-frame poses (a batched Pose), plus the sharp radiance and
    depth at the mid-exposure pose ``mid``. Scans over poses so memory stays O(H·W)."""
    h, w = camera.height, camera.width

    def step(acc, T):
        rad, _ = _render_core(arrays, camera, T, gamma)
        return acc + rad, None

    total, _ = jax.lax.scan(step, jnp.zeros((h, w), jnp.float32), poses)
    sharp, depth = _render_core(arrays, camera, mid, gamma)
    return total / poses.t.shape[0], sharp, depth

