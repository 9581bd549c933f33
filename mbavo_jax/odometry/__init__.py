"""Motion-blur-aware visual odometry over a sequence: the loop (``run``), its per-frame state
(``state``), the RGB-D pipeline's step (``rgbd``) and the run's files (``outputs``)."""

from .outputs import RunOutputs
from .rgbd import RGBDPipeline, keyframe_stats, needs_keyframe
from .run import resume_state, run_odometry
from .state import FrameOutcome, KeyframeState, NewKeyframe, PendingDeblur, Pipeline, RunState, Triptych

__all__ = ["run_odometry", "resume_state", "RGBDPipeline", "RunOutputs", "RunState", "FrameOutcome", "KeyframeState",
           "NewKeyframe", "PendingDeblur", "Pipeline", "Triptych", "needs_keyframe", "keyframe_stats"]
