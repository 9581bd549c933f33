"""The memory a run's settings need, checked before the run starts.

Two programs dominate a run's peak: a pyramid level's solve, which materialises per-sample arrays
for n virtual frames x (points x 8) residuals (the blur synthesis, the per-sample Jacobians g_i and
their contraction with M_i), and keyframe deblurring, whose blur operator and its transpose keep
per-sample weights for n virtual frames x every pixel. Levels, frames and keyframes are processed one
at a time, so the peak is the runtime's base plus the larger of the two. The constants are upper
bounds fitted to the peak resident memory of runs on CPU.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib

from ..config import PATTERN_SIZE, RunConfig, TrackerConfig
from ..errors import ConfigError
from .tracker import _n_for_level

__all__ = ["MemoryEstimate", "tracking_samples", "deblurring_samples", "estimate_memory", "available_memory", "check_memory"]

GIB = 2**30
BASE_BYTES = 1.5e9  # JAX runtime, the compiled level and deblurring programs, the sequence's images
SOLVE_BYTES = {"tangent": 320, "analytic": 320, "autodiff": 640}  # per (virtual frame x residual) of a level's solve
DEBLUR_BYTES = 64  # per (virtual frame x pixel) of the deblurring program


@dataclasses.dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a run needs: ``base`` + max(``tracking``, ``deblurring``) = ``total``."""

    base: float
    tracking: float
    deblurring: float

    @property
    def total(self) -> float:
        return self.base + max(self.tracking, self.deblurring)


def _most_virtual_frames(config: TrackerConfig, level: int) -> int:
    """The most virtual frames the tracker uses on ``level`` (adaptive n: its cap, ``n``)."""
    if config.blur_aware and config.n_mode == "adaptive":
        return config.n
    return _n_for_level(config, 0.0, level)


def tracking_samples(config: TrackerConfig, height: int, width: int) -> int:
    """The largest n x residuals of a level (virtual-frame samples live at once in its solve)."""
    eff = config.for_image(height, width)
    return max(_most_virtual_frames(eff, l) * eff.points[l] * PATTERN_SIZE for l in range(eff.levels))


def deblurring_samples(config: RunConfig, height: int, width: int) -> int:
    """n x pixels of keyframe deblurring (n: ``deblur.n``, or its cap ``n_max``); 0 when never deblurred."""
    if math.isinf(config.odometry.deblur_min_blur_px):
        return 0
    n = config.deblur.n if config.deblur.n > 0 else config.deblur.n_max
    return n * height * width


def estimate_memory(config: RunConfig, height: int, width: int) -> MemoryEstimate:
    """An upper bound of the peak memory of ``mbavo track`` on ``height`` x ``width`` images with
    these settings."""
    tracking = SOLVE_BYTES[config.tracker.jacobian] * tracking_samples(config.tracker, height, width)
    return MemoryEstimate(BASE_BYTES, float(tracking), float(DEBLUR_BYTES * deblurring_samples(config, height, width)))


def _cgroup_limit() -> float:
    """The memory limit of this process's cgroup (v2 or v1), infinity when none."""
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = pathlib.Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            return float(text)
    return math.inf


def available_memory() -> tuple[float, str]:
    """(bytes, what they are) a run can use: the accelerator's memory when JAX runs on one, else the
    machine's physical memory (or its cgroup's limit, when lower)."""
    import jax

    device = jax.devices()[0]
    if device.platform != "cpu":
        limit = (device.memory_stats() or {}).get("bytes_limit")
        if limit:
            return float(limit), f"the {device.device_kind} has"
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return float(min(physical, _cgroup_limit())), "this machine has"


def check_memory(config: RunConfig, height: int, width: int, available: tuple[float, str] | None = None) -> None:
    """Raise ConfigError, in one line naming what to lower, when the settings need more memory than
    ``available`` (default :func:`available_memory`) on ``height`` x ``width`` images."""
    est = estimate_memory(config, height, width)
    have, what = available if available is not None else available_memory()
    if est.total <= have:
        return
    t = config.tracker
    if est.tracking >= est.deblurring:
        settings = f"tracker.n={t.n}, tracker.points={list(t.points)}"
        fix = "lower tracker.n or tracker.points" + (" (or use tracker.jacobian=tangent)" if t.jacobian == "autodiff" else "")
    else:
        settings = f"deblur.n={config.deblur.n}, deblur.n_max={config.deblur.n_max}"
        fix = "lower deblur.n_max (or deblur.n), or set odometry.deblur_min_blur_px=.inf to skip deblurring"
    raise ConfigError(f"{settings} need about {est.total / GIB:.0f} GiB at {width}x{height} "
                      f"({what} {have / GIB:.0f} GiB): {fix}")
