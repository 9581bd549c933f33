"""The monocular back-end (DSO's, as MBA-VO uses it): the fixed-shape window of keyframes and points
(``window``), its photometric bundle adjustment with the Schur complement and marginalisation
(``ba``), candidate points traced along epipolar lines (``candidates``), the two-view initialiser
(``init``) and depth maps of the window's points (``depthmap``). The per-frame pipeline that uses
them is ``odometry.mono.MonoPipeline``.

Bundle adjustment on your own keyframes::

    window = Window.empty(7, 2000, height, width)
    window, slot = add_keyframe(window, linear_image, T_world_kf)
    window, _ = add_points(window, slot, pixels, inverse_depths)
    window, report = bundle_adjust(window, camera, MonoConfig())

Keyframes recorded with motion blur: give ``add_keyframe`` the recorded frame (``raw=``) and its
exposure path about ``T_world_kf`` (``exposure=``), and ``bundle_adjust`` ``samples=`` virtual frames.
"""

from .ba import BAReport, bundle_adjust, marginalize
from .candidates import Candidates, estimates, ready, select_candidates, trace
from .init import TwoView, TwoViewTracker
from .window import Window, add_keyframe, add_points, points_of, world_points

__all__ = ["Window", "add_keyframe", "add_points", "world_points", "points_of", "bundle_adjust", "marginalize", "BAReport",
           "Candidates", "select_candidates", "trace", "ready", "estimates", "TwoView", "TwoViewTracker"]
