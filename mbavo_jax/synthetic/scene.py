"""Ray-cast scenes of textured axis-aligned boxes: a room, hall or other enclosure seen from inside
plus boxes in it (``make_scene``: room, cluttered, deep, distant), or one plane seen obliquely
(plane: its boxes turned about the camera paths' centre, ``Scene.placement``). Textures: procedural
noise, tiles and blobs with photos from the shared data folder (mixed), or photo-like dead-leaves
textures with natural images' 1/f amplitude spectrum on every surface (photo: :func:`dead_leaves`).

Rendering returns linear radiance and z-depth for a camera pose ``T_world_cam``; it is jit-compiled
and renders many sub-frame poses in one call (``render_exposure``), averaging radiance over the
exposure before the camera response is applied. ``render_rolling_exposure`` does the same with a
pose per image row (a rolling shutter: each row at its own times).
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

__all__ = [
    "Scene", "SCENES", "CAMERA_REGION", "make_textures", "make_scene", "default_scene", "cluttered_scene", "deep_scene",
    "distant_scene", "plane_scene", "texels_per_metre", "scene_arrays", "render_exposure", "render_rolling_exposure", "dead_leaves",
    "photo_textures", "TEXTURES",
]

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
    placement: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3, 4, dtype=np.float32))
    """(3, 4) [R | b]: world point p lies at R p + b in the boxes' frame (identity: the boxes are in
    the world frame; R turns about the camera paths' centre, so distances from it are kept)."""


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


def dead_leaves(rng, size: int, r_min: float = 2.0, r_max: float | None = None, cover: float = 8.0) -> np.ndarray:
    """A tileable dead-leaves texture (Lee, Mumford & Huang 2001, "Occlusion models for natural
    images"): opaque discs of uniform random grey dropped one over another, radii with density
    ∝ r⁻³ on [``r_min``, ``r_max``] (default size/4), until each pixel lies under ``cover`` discs on
    average. Scale-invariant sizes and occluding edges give natural images' statistics: an amplitude
    spectrum falling as 1/f. Display values in [0, 1], (size, size)."""
    r_max = r_max or size / 4
    a, b = r_min**-2.0, r_max**-2.0
    mean_area = np.pi * 2.0 / (a - b) * np.log(r_max / r_min)  # E[π r²] under the r⁻³ density
    n = int(np.ceil(cover * size * size / mean_area))
    radii = (a - rng.uniform(size=n) * (a - b)) ** -0.5  # inverse of the r⁻³ CDF
    centres, grey = rng.uniform(0, size, (n, 2)), rng.uniform(size=n)
    img = np.full((size, size), 0.5, np.float32)
    for (x, y), r, g in zip(centres, radii, grey):
        for dx in (0, size, -size):
            for dy in (0, size, -size):
                if -r <= x + dx <= size + r and -r <= y + dy <= size + r:  # the copies that reach the tile: tileable
                    cv2.circle(img, (int(16 * (x + dx)), int(16 * (y + dy))), int(16 * r), float(g), -1, cv2.LINE_8, 4)
    return _normalise(cv2.GaussianBlur(img, (0, 0), 0.6))


def photo_textures(seed: int, size: int = TEXTURE_SIZE, count: int = 6):
    """``count`` dead-leaves textures (:func:`dead_leaves`) and their names."""
    rng = np.random.default_rng(seed + 11)
    return np.stack([dead_leaves(rng, size) for _ in range(count)]), ("photo",) * count


def default_shared_data() -> pathlib.Path | None:
    """The real-data folder: ``$MBAVO_SHARED_DATA``, else ``../shared/data`` beside the working
    directory or beside the repository holding this package (so that generated data does not
    depend on where a command runs); None when none exists."""
    env = os.environ.get("MBAVO_SHARED_DATA")
    if env:
        return pathlib.Path(env)
    for root in (pathlib.Path.cwd(), pathlib.Path(__file__).resolve().parents[2]):
        if (root.parent / "shared" / "data").is_dir():
            return root.parent / "shared" / "data"
    return None


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
        for name, img in _real_images(pathlib.Path(shared_data) if shared_data is not None else default_shared_data()):
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


# The camera paths of every preset (speed <= 1.2 m/s) stay in this region; scenes keep clear of it.
CAMERA_REGION = np.array([[-0.9, -0.35, -1.2], [0.9, 0.35, 0.2]])
CAMERA_CENTRE = np.array([0.0, 0.0, -0.5])
FOCAL_640 = 525.0  # focal length (px) of a 640-wide image


def texels_per_metre(distance):
    """Texture scale for a surface seen from ``distance`` m: one texel per pixel at 640 wide (the
    renderer does not mip-map, so finer textures alias into frame-to-frame noise)."""
    return FOCAL_640 / np.asarray(distance, np.float64)


def _box_distance(box) -> float:
    """Distance from the camera path's centre to the nearest point of ``box`` (2, 3)."""
    nearest = np.clip(CAMERA_CENTRE, box[0], box[1])
    return float(np.linalg.norm(nearest - CAMERA_CENTRE))


def _clear_of_camera(box, clearance: float = 1.0) -> bool:
    """Whether ``box`` (2, 3) stays ``clearance`` m away from every camera path (``CAMERA_REGION``)."""
    gap = np.maximum(0.0, np.maximum(CAMERA_REGION[0] - box[1], box[0] - CAMERA_REGION[1]))
    return float(np.linalg.norm(gap)) >= clearance


def _direction(yaw, pitch) -> np.ndarray:
    """Unit vector ``yaw`` rad to the right of +z and ``pitch`` rad above it (y points down)."""
    return np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])


def _assemble(boxes, inside, tpm, rng, textures, names) -> Scene:
    """A Scene of ``boxes`` with seeded random textures (the enclosing box, first, gets texture 0 or
    a real photo when there is one)."""
    k = len(boxes)
    texture = rng.integers(0, len(names), size=k)
    texture[0] = 6 if len(names) > 6 else 0
    return Scene(
        boxes=np.stack(boxes).astype(np.float32),
        inside=np.asarray(inside, bool),
        texture=texture.astype(np.int32),
        texels_per_m=np.asarray(tpm, np.float32),
        textures=textures.astype(np.float32),
        texture_names=names,
    )


def _box(centre, half) -> np.ndarray:
    """The box (2, 3) [min, max] of ``centre`` and half-sizes ``half``."""
    centre, half = np.asarray(centre, float), np.asarray(half, float)
    return np.stack([centre - half, centre + half])


def cluttered_scene(seed: int = 0, use_real_textures: bool = True, shared_data=None) -> Scene:
    """The room of :func:`default_scene` with 26 smaller boxes 1.6-5 m from the camera in the
    directions it looks (yaw ±60°, pitch ±40°), overlapping in view: many occlusion edges. Every box
    keeps 1 m from the camera paths."""
    textures, names = make_textures(seed, use_real=use_real_textures, shared_data=shared_data)
    rng = np.random.default_rng(seed + 2)
    room = np.array([[-4.0, -2.5, -2.0], [4.0, 2.5, 7.0]])
    boxes, tpm = [room], [110.0]
    while len(boxes) < 27:
        half = rng.uniform([0.08, 0.08, 0.08], [0.45, 0.6, 0.4])
        yaw, pitch = np.deg2rad(rng.uniform(-60, 60)), np.deg2rad(rng.uniform(-40, 40))
        box = _box(CAMERA_CENTRE + rng.uniform(1.6, 5.0) * _direction(yaw, pitch), half)
        if np.all(box[0] > room[0] + 0.05) and np.all(box[1] < room[1] - 0.05) and _clear_of_camera(box):
            boxes.append(box)
            tpm.append(texels_per_metre(_box_distance(box) + half.mean()))
    return _assemble(boxes, [True] + [False] * (len(boxes) - 1), tpm, rng, textures, names)


def _wall_panels(hall, z_edges, thickness: float = 0.05):
    """Thin boxes lining the side walls, floor and ceiling of ``hall`` in segments along z (and one
    on the back wall), each with the texture scale of its own distance from the camera."""
    (x0, y0, z0), (x1, y1, z1) = hall
    boxes, tpm = [np.array([[x0, y0, z0], [x1, y1, z0 + thickness]])], [texels_per_metre(CAMERA_CENTRE[2] - z0)]
    for za, zb in zip(z_edges[:-1], z_edges[1:]):
        dz = abs(0.5 * (za + zb) - CAMERA_CENTRE[2])
        for lo, hi, side in (((x0, y0, za), (x0 + thickness, y1, zb), -x0), ((x1 - thickness, y0, za), (x1, y1, zb), x1),
                             ((x0, y0, za), (x1, y0 + thickness, zb), -y0), ((x0, y1 - thickness, za), (x1, y1, zb), y1)):
            boxes.append(np.array([lo, hi]))
            tpm.append(texels_per_metre(np.hypot(side, dz)))
    return boxes, tpm


def deep_scene(seed: int = 0, use_real_textures: bool = True, shared_data=None) -> Scene:
    """A hall 6 m wide, 4 m high and 46 m long (the camera 5.5 m from its back wall) with 22 boxes
    from 2 m to 35 m ahead: the walls recede from 2 m to 40 m, so views span a wide range of depths."""
    textures, names = make_textures(seed, use_real=use_real_textures, shared_data=shared_data)
    rng = np.random.default_rng(seed + 3)
    hall = np.array([[-3.0, -2.0, -6.0], [3.0, 2.0, 40.0]])
    panels, panel_tpm = _wall_panels(hall, (-6.0, -2.0, 1.0, 3.0, 5.5, 9.0, 14.0, 21.0, 30.0, 40.0))
    boxes, tpm = [hall] + panels, [texels_per_metre(40.5)] + panel_tpm
    for cz in np.geomspace(2.2, 35.0, 22):
        half = (0.12 + 0.03 * cz) * rng.uniform(0.6, 1.4, 3)
        half = np.minimum(half, [1.4, 1.2, 2.0])
        centre = [rng.uniform(-2.9 + half[0], 2.9 - half[0]), rng.uniform(-1.9 + half[1], 1.9 - half[1]), cz]
        boxes.append(_box(centre, half))
        tpm.append(texels_per_metre(_box_distance(boxes[-1]) + half.mean()))
    return _assemble(boxes, [True] + [False] * (len(boxes) - 1), tpm, rng, textures, names)


def distant_scene(seed: int = 0, use_real_textures: bool = True, shared_data=None) -> Scene:
    """A hall 90 m x 60 m x 98 m whose walls, floor, ceiling and 18 boxes are all 25-80 m from
    the camera: translation barely moves pixels, so rotation dominates the blur."""
    textures, names = make_textures(seed, use_real=use_real_textures, shared_data=shared_data)
    rng = np.random.default_rng(seed + 4)
    hall = np.array([[-45.0, -30.0, -42.0], [45.0, 30.0, 56.0]])
    boxes, tpm = [hall], [texels_per_metre(45.0)]
    for _ in range(18):
        yaw, pitch = np.deg2rad(rng.uniform(-100, 100)), np.deg2rad(rng.uniform(-30, 30))
        half = rng.uniform(1.5, 5.0, 3)
        dist = rng.uniform(29.0, 42.0) + np.linalg.norm(half)
        boxes.append(_box(CAMERA_CENTRE + dist * _direction(yaw, pitch), half))
        tpm.append(texels_per_metre(dist))
    return _assemble(boxes, [True] + [False] * (len(boxes) - 1), tpm, rng, textures, names)


PLANE_DISTANCE = 3.0  # m from the camera paths' centre to the plane (paths stay over 1.8 m away)
PLANE_TURN_DEG = (10.0, 30.0)  # the plane's normal turned about x, then about y, from the view axis


def _turn(about_x_deg: float, about_y_deg: float) -> np.ndarray:
    """(3, 4) placement of a turn about x then y, about the camera paths' centre (``Scene.placement``)."""
    ax, ay = np.deg2rad(about_x_deg), np.deg2rad(about_y_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    r = ry @ rx
    return np.concatenate([r, (CAMERA_CENTRE - r @ CAMERA_CENTRE)[:, None]], 1).astype(np.float32)


def plane_scene(seed: int = 0, use_real_textures: bool = True, shared_data=None) -> Scene:
    """One textured plane (80 m x 80 m, a wall or a poster seen obliquely) ``PLANE_DISTANCE`` m
    ahead of the camera paths' centre, its normal turned ``PLANE_TURN_DEG`` from the view axis, so
    its depth changes across the view; a hall 100 m across is the far background that only views
    turned past the plane's edge see."""
    textures, names = make_textures(seed, use_real=use_real_textures, shared_data=shared_data)
    rng = np.random.default_rng(seed + 5)
    hall, wall = _box(CAMERA_CENTRE, [50.0, 50.0, 50.0]), _box(CAMERA_CENTRE + [0.0, 0.0, PLANE_DISTANCE + 0.05], [40.0, 40.0, 0.05])
    scene = _assemble([hall, wall], [True, False], [texels_per_metre(50.0), texels_per_metre(4.0)], rng, textures, names)
    return dataclasses.replace(scene, placement=_turn(*PLANE_TURN_DEG))


SCENES = {"room": default_scene, "cluttered": cluttered_scene, "deep": deep_scene, "distant": distant_scene, "plane": plane_scene}
TEXTURES = ("mixed", "photo")


def make_scene(name: str, seed: int = 0, use_real_textures: bool = True, shared_data=None, texture: str = "mixed") -> Scene:
    """The scene called ``name`` (one of ``SCENES``: room, cluttered, deep, distant, plane), with
    its own textures (``texture`` mixed) or dead-leaves ones on every surface (photo)."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r} (choose from {', '.join(SCENES)})")
    if texture not in TEXTURES:
        raise ValueError(f"unknown texture {texture!r} (choose from {', '.join(TEXTURES)})")
    scene = SCENES[name](seed, use_real_textures=use_real_textures and texture == "mixed", shared_data=shared_data)
    if texture == "photo":
        textures, names = photo_textures(seed)
        scene = dataclasses.replace(scene, textures=textures, texture_names=names, texture=scene.texture % len(names))
    return scene


def scene_arrays(scene: Scene):
    """The scene as device arrays (boxes, inside, texture index, texels per metre, textures, placement)."""
    return (
        jnp.asarray(scene.boxes),
        jnp.asarray(scene.inside),
        jnp.asarray(scene.texture),
        jnp.asarray(scene.texels_per_m),
        jnp.asarray(scene.textures),
        jnp.asarray(scene.placement, jnp.float32),
    )


def _rays(camera: PinholeCamera, T_world_cam: Pose):
    """World ray directions (h, w, 3), with camera z = 1, and origins (3,) or, for a pose per image
    row (a Pose batched over the h rows: a rolling shutter), (h, 1, 3)."""
    h, w = camera.height, camera.width
    u, v = jnp.meshgrid(jnp.arange(w, dtype=jnp.float32), jnp.arange(h, dtype=jnp.float32))
    d_cam = jnp.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, jnp.ones_like(u)], -1)
    if T_world_cam.t.ndim == 1:
        return d_cam @ T_world_cam.rotation().T, T_world_cam.t
    R = jax.vmap(lambda T: T.rotation())(T_world_cam)  # (h, 3, 3)
    return jnp.einsum("vuj,vij->vui", d_cam, R), T_world_cam.t[:, None, :]


def _render_core(arrays, camera: PinholeCamera, T_world_cam: Pose, gamma):
    """Linear radiance and depth (h, w) seen from ``T_world_cam``: one pose, or one per image row."""
    boxes, inside, tex_idx, tpm, textures, placement = arrays
    h, w = camera.height, camera.width
    d, o = _rays(camera, T_world_cam)  # camera z of the hit equals the ray parameter t
    d, o = d @ placement[:, :3].T, o @ placement[:, :3].T + placement[:, 3]  # into the boxes' frame (a rigid turn keeps t)
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


@jax.jit
def render_rolling_exposure(arrays, camera: PinholeCamera, row_poses: Pose, gamma=2.2) -> jax.Array:
    """Mean linear radiance (h, w) of a rolling-shutter exposure: ``row_poses`` is a Pose batched
    (S, h), sub-frame k of row v at ``row_poses[k, v]``; each row is the mean of its S renders.
    Scans over the S sub-frames (each a whole image, every row at its own pose), so memory stays
    O(H·W) and the cost is that of S global-shutter renders."""
    h, w = camera.height, camera.width

    def step(acc, T):
        rad, _ = _render_core(arrays, camera, T, gamma)
        return acc + rad, None

    total, _ = jax.lax.scan(step, jnp.zeros((h, w), jnp.float32), row_poses)
    return total / row_poses.t.shape[0]

