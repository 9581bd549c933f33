"""Motion-blur-aware visual odometry over a sequence: the loop (``run``), its per-frame state
(``state``), the RGB-D pipeline's step (``rgbd``), the monocular one's (``mono``), the online exposure estimate (``exposure``) and
the run's files (``outputs``)."""

from .exposure import ExposureEstimate, RawFrame, exposure_mode, pair_sample, pick_pair
from .outputs import RunOutputs
from .rgbd import RGBDPipeline, needs_keyframe
from .stats import PointStats, keyframe_stats
from .mono import MonoPipeline, MonoState, PointCloud
from .run import choose_pipeline, resume_state, run_odometry
from .state import ExposureReport, FrameOutcome, KeyframeState, NewKeyframe, PendingDeblur, Pipeline, RunState, Triptych

__all__ = ["run_odometry", "resume_state", "choose_pipeline", "RGBDPipeline", "MonoPipeline", "MonoState", "PointCloud", "RunOutputs", "RunState", "FrameOutcome", "KeyframeState",
           "NewKeyframe", "PendingDeblur", "Pipeline", "Triptych", "ExposureReport", "ExposureEstimate", "PointStats",
           "RawFrame", "exposure_mode", "pick_pair", "pair_sample", "needs_keyframe", "keyframe_stats"]
