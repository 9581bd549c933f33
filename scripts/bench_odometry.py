#!/usr/bin/env python3
"""Odometry results table (same as `mbavo bench odometry`): ATE (SE3) and frame drops on generated
640x480 sequences at blur none / mild / strong / extreme and on the blurred TUM fr1/xyz clip, for
ours n=64, ours n=1 (blur-unaware), ours adaptive n, and Open3D RGB-D odometry; plus PSNR/SSIM of the
deblurred keyframes. Example: python scripts/bench_odometry.py --frames 50
"""

import sys

from mbavo_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "odometry", *sys.argv[1:]]))
