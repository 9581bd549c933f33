"""``mbavo bench``: the benchmarks, one module each, and the data they share.

* ``sequences``: the generated sequences of the blur presets, their exposure-hidden copies, the real
  clips, the tracking benchmark's frame pairs;
* ``tracking``: frame pairs, ours against Open3D and OpenCV (``mbavo bench tracking``);
* ``odometry``: whole sequences as a sweep, ATE and frame drops (``mbavo bench odometry``);
* ``speed``: where the loop's time goes, start-up, memory (``mbavo bench speed``);
* ``mono``: the monocular system against n = 1 and the RGB-D loop (``mbavo bench mono``);
* ``dso``: DSO as a peer of ``mbavo bench mono`` (its dataset layout, a subprocess run, its result read);
* ``rolling``: the rolling-shutter model and the cubic path (``mbavo bench rolling-shutter``).

A method's run over a sequence (ours or a peer) is ``mbavo_jax.methods``'s, which the sweep's workers
call too; the peers' adapters are ``mbavo_jax.peers``. Each command's ``main_*`` is imported on first
use (PEP 562), so that importing one benchmark loads no other.
"""

__all__ = ["main_tracking", "main_odometry", "main_speed", "main_mono", "main_rolling"]


def __getattr__(name: str):
    """The commands' entry points, each imported from its module on first use."""
    if name == "main_tracking":
        from .tracking import main_tracking

        return main_tracking
    if name == "main_odometry":
        from .odometry import main_odometry

        return main_odometry
    if name == "main_speed":
        from .speed import main_speed

        return main_speed
    if name == "main_mono":
        from .mono import main_mono

        return main_mono
    if name == "main_rolling":
        from .rolling import main_rolling

        return main_rolling
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
