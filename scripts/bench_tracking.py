#!/usr/bin/env python3
"""Tracking benchmark (same as `mbavo bench tracking`): ours n=1 / n=64 autodiff / n=64 analytic /
n=64 tangent (the default) / adaptive n vs Open3D and OpenCV RGB-D odometry on the same frames of a generated 640x480 sequence.

Open3D comes with `pip install -e ".[bench]"` (or the test extra).
"""

import sys

from mbavo_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "tracking", *sys.argv[1:]]))
