"""The generator's smooth camera path, a closed form in time (so the simulated IMU differentiates it exactly)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry import quaternion as quat
from ..geometry.pose import Pose

__all__ = ["camera_path"]


def camera_path(t, speed: float, rotation_rate: float, seed: int = 0, shake_deg: float = 0.0, shake_hz: float = 12.0) -> Pose:
    """``T_world_cam`` at time t (s): a smooth Lissajous path inside the room, looking along +z.

    Peak linear speed ≈ ``speed`` m/s, peak angular rate ≈ ``rotation_rate`` deg/s. ``shake_deg`` > 0
    adds a handheld shake: rotations of that amplitude about x and y at ``shake_hz``, a quarter
    period apart, so the view circles and a path spanning a good part of its period is curved.
    """
    rng = np.random.default_rng(seed + 7)
    ph = rng.uniform(0, 2 * np.pi, size=6)
    w = 2 * np.pi * np.array([0.23, 0.31, 0.17, 0.41, 0.29, 0.19])
    t = jnp.asarray(t, jnp.float32)
    a = speed / w[0]
    pos = jnp.stack(
        [
            a * jnp.sin(w[0] * t + ph[0]),
            0.5 * a * w[0] / w[1] * jnp.sin(w[1] * t + ph[1]),
            0.6 * a * w[0] / w[2] * jnp.sin(w[2] * t + ph[2]) - 0.5,
        ]
    )
    b = np.deg2rad(rotation_rate) / w[3]
    rot = jnp.stack(
        [
            0.6 * b * jnp.sin(w[4] * t + ph[4]) * w[3] / w[4],
            b * jnp.sin(w[3] * t + ph[3]),
            0.3 * b * jnp.sin(w[5] * t + ph[5]) * w[3] / w[5],
        ]
    )
    if shake_deg > 0:
        phase = float(2 * np.pi * shake_hz) * t + float(rng.uniform(0, 2 * np.pi))
        rot = rot + np.deg2rad(shake_deg) * jnp.stack([jnp.sin(phase), jnp.cos(phase), jnp.zeros_like(phase)])
    return Pose(quat.exp(rot), pos)
