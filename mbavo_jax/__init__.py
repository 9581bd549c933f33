"""mbavo_jax: motion-blur-aware direct visual odometry (MBA-VO, Liu et al., ICCV 2021) in JAX.

Conventions (used everywhere, never mixed):

* Quaternions are ``[qx, qy, qz, qw]`` (Hamilton), as in the paper. TUM trajectory files are
  ``timestamp tx ty tz qx qy qz qw``.
* ``T_a_b`` maps points of frame b into frame a: ``p_a = T_a_b.apply(p_b)`` (the paper's T_b^a).
* A frame's exposure path is ``ExposureTrajectory(start=T_ref_start, end=T_ref_end)``; virtual pose
  i of n sits at s = i/(n-1) (s = 1/2 when n = 1), rotation by quaternion exp/log (Eq. 43),
  translation linearly (Eq. 44).
* Output trajectories are camera-to-world (``T_world_cam``), one pose per frame, stamped at
  mid-exposure.
* Pixel centres are at integer coordinates; intensities are float in [0, 1].
"""

__version__ = "0.1.0"
__all__ = ["Pose", "PinholeCamera", "ExposureTrajectory", "__version__"]

_GEOMETRY = ("Pose", "PinholeCamera", "ExposureTrajectory")


def __getattr__(name: str):
    """The geometry types, imported on first use (PEP 562): ``import mbavo_jax.cli`` loads no JAX."""
    if name in _GEOMETRY:
        from . import geometry

        return getattr(geometry, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_GEOMETRY])
