"""DSO (Engel, Koltun, Cremers 2018) as a peer of ``mbavo bench mono``: a ``dso_dataset`` binary
the user built (``../shared/tools/build_dso.sh``) run as a subprocess on any sequence we can open.

* :func:`write_dso_folder`: the sequence in DSO's dataset layout (its ``util/DatasetReader.h``):
  ``images/`` (8-bit grey, names in frame order: DSO sorts them), ``times.txt`` (``id timestamp``,
  no exposure: see below) and ``camera.txt`` (``Pinhole fx fy cx cy 0``, ``W H``, ``none`` or
  ``crop``, ``W_out H_out``; :func:`dso_output_size`).
* :func:`run_dso`: ``dso_dataset files=DIR/images calib=DIR/camera.txt preset=0 mode=1 nogui=1
  nolog=1 quiet=1`` in the run folder, with a timeout; its output kept as ``dso.log``; its
  ``result.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world, every tracked frame) read
  by :func:`read_dso_result` and written as the run's ``trajectory.txt`` (TUM, the sequence's own
  stamps), so that it is scored as our runs are.

Exposure: ``mode=1`` runs DSO without photometric calibration (the images are not radiance). DSO
uses an exposure time only as the ratio ``exposure_target / exposure_host`` that scales its affine
brightness model (``AffLight::fromToVecExposure``), which holds for linear images only; a
``times.txt`` without exposures (or with zeros) makes it use 1 for every frame
(``ImageFolderReader::loadTimestamps``) and leaves brightness changes to the affine parameters.
So no exposure is written: right for images with a camera response, the same as the true value
where the exposure is constant, and fair to our runs on sequences whose exposure is hidden.
Restarts: DSO starts afresh ("RESETTING!" in its output) when its initialisation fails, and its
``result.txt`` then holds the frames after the last restart only; "LOST!!" ends the run.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import time

import numpy as np

from ..errors import DataError, MbavoError
from ..io import data_lines, read_tum_trajectory, write_tum_trajectory

__all__ = ["DSO_ARGS", "dso_output_size", "write_dso_folder", "read_dso_result", "dso_restarts", "check_dso_binary", "run_dso"]

DSO_ARGS = ("preset=0", "mode=1", "nogui=1", "nolog=1", "quiet=1")  # no real-time playback, no photometric calibration
DSO_BLOCK = 16  # DSO's pyramid halves the image until it is small: sizes that are multiples of 16 need no resampling
RESET_LINE, LOST_LINE = "RESETTING!", "LOST!!"


def dso_output_size(width: int, height: int) -> tuple[str, int, int]:
    """camera.txt's last two lines for a ``width`` x ``height`` pinhole camera: ("none", W, H) when
    both are multiples of 16; else ("crop", W_out, H_out): both scaled by the smaller of
    floor16(W)/W and floor16(H)/H and rounded to multiples of 16, so that pixels stay near square
    (DSO's crop resamples the whole view to that size; KITTI 1241x376 -> 1216x368)."""
    if width % DSO_BLOCK == 0 and height % DSO_BLOCK == 0:
        return "none", width, height
    s = min((width // DSO_BLOCK) * DSO_BLOCK / width, (height // DSO_BLOCK) * DSO_BLOCK / height)
    fit = lambda n: max(DSO_BLOCK, int(round(n * s / DSO_BLOCK)) * DSO_BLOCK)
    return "crop", fit(width), fit(height)


def _camera_txt(camera) -> str:
    """DSO's camera.txt of a pinhole camera (pixel centres at integer coordinates, as DSO's; the float32 values exactly)."""
    mode, w_out, h_out = dso_output_size(camera.width, camera.height)
    fx, fy, cx, cy = (np.format_float_positional(np.float32(v), unique=True, trim="-") for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    return f"Pinhole {fx} {fy} {cx} {cy} 0\n{camera.width} {camera.height}\n{mode}\n{w_out} {h_out}\n"


def write_dso_folder(seq, folder) -> pathlib.Path:
    """``seq`` (any sequence :func:`mbavo_jax.datasets.open_sequence` opens: frames undistorted,
    grey in [0, 1]) in DSO's layout under ``folder``: images/000000.png ..., times.txt, camera.txt.
    Returns ``folder/images``, DSO's ``files=`` argument."""
    import cv2

    folder = pathlib.Path(folder)
    images = folder / "images"
    images.mkdir(parents=True, exist_ok=True)
    for old in images.glob("*.png"):
        old.unlink()
    for i in range(len(seq)):
        pixels = np.clip(np.round(np.asarray(seq[i].image, np.float64) * 255.0), 0, 255).astype(np.uint8)
        if not cv2.imwrite(str(images / f"{i:06d}.png"), pixels):
            raise MbavoError(f"{images / f'{i:06d}.png'}: cannot write DSO's input image")
    (folder / "times.txt").write_text("".join(f"{i} {float(t)!r}\n" for i, t in enumerate(seq.timestamps)))
    (folder / "camera.txt").write_text(_camera_txt(seq.camera))
    return images


def read_dso_result(path, stamps) -> tuple[np.ndarray, np.ndarray]:
    """DSO's result.txt (TUM lines, strictly checked by :func:`mbavo_jax.io.read_tum_trajectory`),
    each stamp replaced by the sequence's ``stamps`` entry it is (DSO prints 15 digits): (frame
    indices (N,), poses (N, 7)). No line: no pose (DSO never initialised). A stamp further than a
    quarter of the frame interval from every frame is a DataError naming its line."""
    from ..evaluation.associate import associate

    path = pathlib.Path(path)
    lines = data_lines(path, "DSO result file")
    if not lines:
        return np.zeros(0, np.int64), np.zeros((0, 7))
    t, poses = read_tum_trajectory(path)
    stamps = np.asarray(stamps, np.float64)
    tol = 0.25 * float(np.min(np.diff(stamps))) if len(stamps) > 1 else 1e-3
    matched, index = associate(t, stamps, tol)
    if len(matched) < len(t):
        k = int(np.setdiff1d(np.arange(len(t)), matched)[0])
        raise DataError(path, f"timestamp {float(t[k])!r} is no frame of the sequence (none within {tol:.3g} s)", lines[k][0])
    return index, poses


def dso_restarts(log: str) -> int:
    """How often DSO started afresh ("RESETTING!" lines in its output)."""
    return sum(line.strip() == RESET_LINE for line in log.splitlines())


def check_dso_binary(path) -> pathlib.Path:
    """``path`` as an executable file; MbavoError (one line) otherwise."""
    p = pathlib.Path(path).expanduser()
    if not p.is_file() or not os.access(p, os.X_OK):
        raise MbavoError(f"--dso {path}: not an executable file (build DSO's dso_dataset with ../shared/tools/build_dso.sh)")
    return p.resolve()


def _last_line(log: str) -> str:
    lines = [s.strip() for s in log.splitlines() if s.strip()]
    return lines[-1][:120] if lines else "no output"


def run_dso(seq, run, binary, timeout_s: float) -> dict:
    """DSO over ``seq`` in the run folder ``run``: its input in ``run/input``, its output in
    ``run/dso.log``, its poses in ``run/trajectory.txt`` (TUM, camera-to-world, the sequence's
    stamps). Returns the frames, the frames posed, restarts, whether DSO said it was lost and the
    seconds per frame (the whole process: start, reading images, tracking, mapping). A timeout,
    a crash without result.txt or a malformed result is one MbavoError line."""
    binary, run = check_dso_binary(binary), pathlib.Path(run)
    run.mkdir(parents=True, exist_ok=True)
    for old in ("result.txt", "trajectory.txt", "dso.log"):
        (run / old).unlink(missing_ok=True)
    images = write_dso_folder(seq, run / "input")
    cmd = [str(binary), f"files={images.resolve()}", f"calib={(run / 'input' / 'camera.txt').resolve()}", *DSO_ARGS]
    t0 = time.perf_counter()
    with open(run / "dso.log", "w") as log:
        try:
            rc = subprocess.run(cmd, cwd=run, stdout=log, stderr=subprocess.STDOUT, timeout=timeout_s, check=False).returncode
        except subprocess.TimeoutExpired:
            raise MbavoError(f"{binary}: DSO did not finish in {timeout_s:g} s (bench.dso_timeout; its output: {run / 'dso.log'})") from None
    seconds, text = time.perf_counter() - t0, (run / "dso.log").read_text(errors="replace")
    if not (run / "result.txt").is_file():
        raise MbavoError(f"{binary}: DSO exited with status {rc} and wrote no result.txt ({_last_line(text)}; {run / 'dso.log'})")
    index, poses = read_dso_result(run / "result.txt", seq.timestamps)
    if len(index):
        write_tum_trajectory(run / "trajectory.txt", np.asarray(seq.timestamps)[index], poses, "timestamp tx ty tz qx qy qz qw (DSO, camera-to-world)")
    return {"frames": len(seq), "posed": int(len(index)), "restarts": dso_restarts(text), "lost": LOST_LINE in text,
            "exit_status": rc, "seconds_per_frame": seconds / max(len(seq), 1)}
