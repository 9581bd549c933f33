"""Bad input gets one clear line and loses nothing.

Each row of ``CASES`` is an ordinary user mistake: an output folder that cannot be made (``--out`` /
``--plot`` naming a file, ``/dev/null/x``, ``/proc/x``), text that is not UTF-8 (lists, trajectories,
camera.yaml, ``--config``), a camera.yaml with a bad value, out-of-range options of ``eval``,
``synth`` (also ``--from``) and ``deblur``, non-finite and repeated timestamps, a frame of the wrong
size, a synthetic sequence too large for the machine. Each runs ``mbavo`` in-process on a copy of a
tiny generated sequence (corrupted by the row's ``setup``) and must exit 1 with exactly one line
``mbavo: error: ...`` on stderr holding the row's ``expect``, print nothing on stdout, show no
traceback nor ``np.float64(...)``, and leave every file as it was (nothing half-written).

To add a row: a ``Case`` with an id, the arguments (``{seq}``: the sequence copy, ``{tmp}``: the
test's folder, ``{file}``: a regular file in it) and the expected part of the error line.
"""

from __future__ import annotations

import dataclasses
import pathlib
import shutil
from typing import Callable

import cv2
import numpy as np
import pytest

from mbavo_jax.errors import FrameIndexError, MbavoError

Setup = Callable[[pathlib.Path], None]


@dataclasses.dataclass(frozen=True)
class Case:
    """One mistake: ``argv`` after ``mbavo`` and the text ``expect`` the error line must hold (both with
    the placeholders ``{seq}``, ``{tmp}``, ``{file}``); ``setup`` corrupts the sequence copy first."""

    id: str
    argv: tuple[str, ...]
    expect: str
    setup: Setup | None = None


# ------------------------------------------------------------------------------ corrupting a copy


def prepend(name: str, data: bytes) -> Setup:
    """Put ``data`` before the first line of ``name``."""
    return lambda seq: (seq / name).write_bytes(data + (seq / name).read_bytes())


def edit_line(name: str, line: int, old: bytes, new: bytes) -> Setup:
    """Replace ``old`` by ``new`` on line ``line`` (1-based) of ``name``."""

    def setup(seq: pathlib.Path) -> None:
        lines = (seq / name).read_bytes().split(b"\n")
        assert old in lines[line - 1], (name, line, lines[line - 1])
        lines[line - 1] = lines[line - 1].replace(old, new, 1)
        (seq / name).write_bytes(b"\n".join(lines))

    return setup


def camera(key: str, value: str) -> Setup:
    """Set camera.yaml's ``key`` to the YAML text ``value``."""

    def setup(seq: pathlib.Path) -> None:
        kept = [ln for ln in (seq / "camera.yaml").read_text().splitlines() if not ln.startswith(f"{key}:")]
        (seq / "camera.yaml").write_text("\n".join(kept + [f"{key}: {value}"]) + "\n")

    return setup


def image(name: str, height: int, width: int, dtype=np.uint8) -> Setup:
    """Overwrite the image ``name`` with a grey one of another size."""
    return lambda seq: cv2.imwrite(str(seq / name), np.full((height, width), 100, dtype))


def write(name: str, data: bytes) -> Setup:
    return lambda seq: (seq / name).write_bytes(data)


def remove(name: str) -> Setup:
    return lambda seq: (seq / name).unlink()


def run_folder(keyframes: bool = True, image: bytes | None = None, record: Callable[[pathlib.Path], dict] | None = None) -> Setup:
    """An earlier run of the sequence in ``{tmp}/run`` (two committed frames: frames.csv, trajectory,
    exposure, keyframes.txt unless not ``keyframes``, the keyframe image ``image`` (default: the first
    frame), and ``record(seq)`` as run.yaml when given), as a kill would leave it."""

    def setup(seq: pathlib.Path) -> None:
        from mbavo_jax.odometry.outputs import CSV_COLUMNS

        run, pose = seq.parent / "run", "0 0 0 0 0 0 1"
        (run / "keyframes").mkdir(parents=True)
        (run / "trajectory.txt").write_text(f"# t\n1.000000 {pose}\n{FRAME1} {pose}\n")
        (run / "exposure.txt").write_text(f"# t\n1.000000 {pose} {pose}\n{FRAME1} {pose} {pose}\n")
        if keyframes:
            (run / "keyframes.txt").write_text(f"# t\n1.000000 {pose}\n")
        cells = lambda *v: ",".join(map(str, v)) + "," * (len(CSV_COLUMNS) - len(v)) + "\n"
        (run / "frames.csv").write_text(",".join(CSV_COLUMNS) + "\n" + cells(0, "1.000000", "keyframe", 0.0, 0, 0.0, "", 0.0, 1)
                                        + cells(1, FRAME1, "converged", 0.01, 60, 1.0, "initial guess", 5.0, 0))
        kf = image if image is not None else cv2.imencode(".png", cv2.imread(str(seq / "rgb" / "1.000000.png"), 0).astype(np.uint16) * 257)[1].tobytes()
        (run / "keyframes" / "1.000000.png").write_bytes(kf)
        if record is not None:
            import yaml

            (run / "run.yaml").write_text(yaml.safe_dump(record(seq)))

    return setup


def run_record(digest: str | None = None, **tracker) -> Callable[[pathlib.Path], dict]:
    """run.yaml of a run of the sequence (``digest``: another sequence's) with the default settings
    but ``tracker`` (and the sequence's camera.yaml calibration)."""

    def record(seq: pathlib.Path) -> dict:
        from mbavo_jax.config import as_dict, calibration_of, load_config
        from mbavo_jax.datasets import open_sequence
        from mbavo_jax.odometry.folder import sequence_fingerprint

        sequence = open_sequence(seq)
        settings = as_dict(load_config(None, [f"tracker.{k}={v}" for k, v in tracker.items()], calibration_of(sequence.meta)))
        fingerprint = {**sequence_fingerprint(sequence), **({"digest": digest} if digest else {})}
        return {"sequence": fingerprint, "segments": [{"first_frame": 0, "resume_anyway": False, "settings": settings}]}

    return record


# -------------------------------------------------------------------------------------- the table

FRAME1 = "1.033333"  # the stamp of frame 1 (rgb.txt and depth.txt line 4, times.txt line 3)
TINY = ("--frames", "1", "--width", "16", "--height", "16", "-q")
GT, EXP = "{seq}/groundtruth.txt", "{seq}/exposure.txt"
DEBLUR = ("deblur", "{seq}", "--frame", "1")
OUTSIDE = [("file", "{file}", "{file}: --out exists and is not a folder"),
           ("devnull", "/dev/null/x", "/dev/null is not a folder"),
           ("proc", "/proc/x", "/proc/x: --out cannot be created")]
TRACK = ("track", "{seq}", "--out", "{tmp}/run", "-q")
TEXT_FILES = ["rgb.txt", "depth.txt", "groundtruth.txt", "times.txt", "exposure.txt", "camera.yaml"]

CASES = [
    # 1. output folders that cannot be made
    *[Case(f"synth_out_{k}", ("synth", "--out", out, *TINY), msg) for k, out, msg in OUTSIDE],
    *[Case(f"deblur_out_{k}", (*DEBLUR, "--out", out), msg) for k, out, msg in OUTSIDE],
    *[Case(f"eval_plot_{k}", ("eval", "ape", GT, GT, "--plot", out), msg.replace("--out", "--plot")) for k, out, msg in OUTSIDE],
    *[Case(f"demo_out_{k}", ("demo", "--out", out, "--frames", "2", "-q"), msg) for k, out, msg in OUTSIDE[:2]],
    # 2. text that is not UTF-8, in a comment or in the data
    *[Case(f"utf8_comment_{n}", ("info", "{seq}"), f"{{seq}}/{n}:1: byte 0xff is not UTF-8", prepend(n, b"# \xff\n"))
      for n in TEXT_FILES],
    Case("utf8_rgb_data_line", ("info", "{seq}"), "{seq}/rgb.txt:4: byte 0xff", edit_line("rgb.txt", 4, b"rgb/", b"rgb/\xff")),
    Case("utf8_config", ("track", "{seq}", "--out", "{tmp}/run", "--config", "{seq}/bad.yaml"), "{seq}/bad.yaml:2: byte 0xff",
         write("bad.yaml", b"tracker:\n  n: 8  # \xff\n")),
    # 3. camera.yaml values
    *[Case(f"camera_{key}_{value}", ("info", "{seq}"), f"{{seq}}/camera.yaml: {expect}", camera(key, value)) for key, value, expect in [
        ("response_gamma", "abc", "camera key 'response_gamma' is not a number"),
        ("response_gamma", ".nan", "camera key 'response_gamma' is not finite"),
        ("fps", "abc", "camera key 'fps' is not a number"),
        ("exposure_ms", "-1", "camera key 'exposure_ms' must be >= 0"),
        ("fx", ".inf", "camera key 'fx' is not finite"),
        ("fx", "0", "camera key 'fx' must be > 0"),
        ("fy", "-1", "camera key 'fy' must be > 0"),
        ("cx", "5000", "principal point cx = 5000 is outside the image"),
        ("cx", "-1", "principal point cx = -1 is outside the image"),
        ("cy", "48", "principal point cy = 48 is outside the image"),
        ("depth_scale", "0", "camera key 'depth_scale' must be > 0"),
        ("depth_scale", "-5", "camera key 'depth_scale' must be > 0"),
        ("width", "64.5", "camera key 'width' must be a whole number"),
    ]],
    # 4. eval options
    Case("eval_exposure_without_camera", ("eval", "exposure", EXP, EXP), "needs --camera"),
    *[Case(f"eval_rpe_delta_{d}", ("eval", "rpe", GT, GT, f"--delta={d}"), "argument --delta: must be >= 1") for d in ("0", "-1")],
    *[Case(f"eval_exposure_depth_{d}", ("eval", "exposure", EXP, EXP, "--camera", "{seq}/camera.yaml", f"--depth={d}"),
           "argument --depth: must be a finite number > 0") for d in ("-1", "0", "nan")],
    Case("eval_t_max_diff_negative", ("eval", "ape", GT, GT, "--t_max_diff=-1"), "argument --t_max_diff: must be a finite number > 0"),
    # 5. synth settings, rendered and --from
    *[Case(f"synth_{flag[2:]}_{value}", ("synth", "--out", "{tmp}/out", *TINY, flag, value), expect) for flag, value, expect in [
        ("--fps", "0", "fps: must be > 0"),
        ("--fps", "-30", "fps: must be > 0"),
        ("--exposure-ms", "-1", "exposure_ms: must be >= 0"),
        ("--noise", "-1", "noise: must be >= 0"),
        ("--noise", "nan", "noise: must be >= 0, got nan"),
        ("--subframes", "0", "subframes: must be >= 1"),
        ("--frames", "0", "frames: must be >= 1"),
    ]],
    *[Case(f"synth_from_{flag[2:]}_{value}", ("synth", "--from", "{seq}", "--out", "{tmp}/out", "-q", flag, value), expect)
      for flag, value, expect in [
        ("--blur-px", "-5", "--blur-px: must be a finite number >= 0, got -5"),
        ("--blur-px", "nan", "--blur-px: must be a finite number >= 0, got nan"),
        ("--subframes", "0", "subframes: must be >= 1"),
        ("--noise", "nan", "noise: must be >= 0, got nan"),
        ("--seed", "-1", "seed: must be >= 0"),
    ]],
    # 6. deblur
    Case("deblur_regularization", (*DEBLUR, "--out", "{tmp}/out", "--regularization", "-1"), "deblur.regularization: must be >= 0"),
    Case("deblur_frame_negative", ("deblur", "{seq}", "--frame", "-1", "--out", "{tmp}/out"), "--frame -1 out of range"),
    Case("deblur_frame_past_end", ("deblur", "{seq}", "--frame", "3", "--out", "{tmp}/out"), "--frame 3 out of range"),
    Case("deblur_no_exposure_file", (*DEBLUR, "--out", "{tmp}/out"), "{seq}: no groundtruth_exposure.txt or exposure.txt",
         remove("exposure.txt")),
    # 7. timestamps: a plain number, blamed on their own line
    Case("stamp_inf_rgb", ("info", "{seq}"), "{seq}/rgb.txt:4: timestamp inf is not a finite number",
         edit_line("rgb.txt", 4, FRAME1.encode(), b"inf")),
    Case("stamp_nan_rgb_check", ("info", "{seq}", "--check", "-q"), "{seq}/rgb.txt:4: timestamp nan is not a finite number",
         edit_line("rgb.txt", 4, FRAME1.encode(), b"nan")),
    Case("stamp_nan_depth", ("info", "{seq}"), "{seq}/depth.txt:4: timestamp nan", edit_line("depth.txt", 4, FRAME1.encode(), b"nan")),
    Case("stamp_nan_times", ("info", "{seq}"), "{seq}/times.txt:3: non-finite value", edit_line("times.txt", 3, FRAME1.encode(), b"nan")),
    Case("stamp_inf_groundtruth", ("info", "{seq}"), "{seq}/groundtruth.txt:3: non-finite value",
         edit_line("groundtruth.txt", 3, FRAME1.encode(), b"inf")),
    Case("stamp_duplicate", ("info", "{seq}"), "{seq}/rgb.txt:4: duplicate timestamp 1.0 (",
         edit_line("rgb.txt", 4, FRAME1.encode(), b"1.000000")),
    # 8. a frame of another size, blamed on its own file
    Case("image_size", ("info", "{seq}", "--check", "-q"), f"{{seq}}/rgb/{FRAME1}.png: image size 64x40 differs from the camera's 64x48",
         image(f"rgb/{FRAME1}.png", 40, 64)),
    Case("depth_size", ("info", "{seq}", "--check", "-q"), f"{{seq}}/depth/{FRAME1}.png: depth size 32x48",
         image(f"depth/{FRAME1}.png", 48, 32, np.uint16)),
    # 9. a sequence too large to render, settings too large to track
    Case("synth_too_large", ("synth", "--out", "{tmp}/out", "--frames", "2", "--width", "100000", "--height", "100000", "-q"),
         "lower --width and --height"),
    Case("track_n_too_large", (*TRACK, "--set", "tracker.n=2000000"), "lower tracker.n or tracker.points"),  # ~1.8 TiB at any size
    # 10. mbavo track: settings out of range, output folders, --max-frames
    *[Case(f"track_set_{item}", (*TRACK, "--set", item), expect) for item, expect in [
        ("tracker.levels=0", "tracker.levels: must be >= 1, got 0"),
        ("tracker.levels=-1", "tracker.levels: must be >= 1, got -1"),
        ("tracker.levels=2.5", "tracker.levels"),
        ("tracker.cell=[0,0,0,0]", "tracker.cell: must be >= 1"),
        ("tracker.cell=[10,10]", "tracker: cell needs one entry per level (4)"),
        ("tracker.huber=-1", "tracker.huber: must be > 0, got -1"),
        ("tracker.huber=nan", "tracker.huber: must be > 0, got nan"),
        ("tracker.max_steps=0", "tracker.max_steps: expected a list, one value per pyramid level"),
        ("tracker.max_steps=[0,1,1,1]", "tracker.max_steps: must be >= 1"),
        ("tracker.points=[0,0,0,0]", "tracker.points: must be >= 1"),
        ("tracker.rtol=nan", "tracker.rtol: must be > 0, got nan"),
        ("tracker.n=0", "tracker.n: must be >= 1, got 0"),
        ("odometry.keyframe_min_visible=2", "odometry.keyframe_min_visible: must be in (0, 1]"),
        ("deblur.regularization=-1", "deblur.regularization: must be >= 0"),
    ]],
    *[Case(f"track_out_{k}", ("track", "{seq}", "--out", out, "-q"), msg) for k, out, msg in OUTSIDE],
    Case("track_max_frames_0", (*TRACK, "--max-frames", "0"), "argument --max-frames: must be >= 1, got 0"),
    Case("argparse_unknown_option", (*TRACK, "--bogus"), "unrecognized arguments: --bogus"),  # exit 1, as every error
    Case("argparse_missing_out", ("track", "{seq}"), "the following arguments are required: --out"),
    Case("track_small_image", (*TRACK, "--set", "tracker.min_valid=1000"), "images are too small to track"),
    # 11. --resume of a run folder that cannot be continued
    Case("resume_without_keyframes_txt", (*TRACK, "--resume"), "{tmp}/run/keyframes.txt: missing, but frames.csv records 2 frames",
         run_folder(keyframes=False)),
    Case("resume_corrupt_keyframe_image", (*TRACK, "--resume"), "{tmp}/run/keyframes/1.000000.png: keyframe image needed for --resume",
         run_folder(image=b"\x89PNG not really")),
    Case("resume_other_sequence", (*TRACK, "--resume"), "--resume of a run made on another sequence",
         run_folder(record=run_record(digest="0123456789abcdef"))),
    Case("resume_other_settings", (*TRACK, "--resume"), "--resume with other settings than the run's (tracker.n: 32 -> 64)",
         run_folder(record=run_record(n=32))),
]


# ---------------------------------------------------------------------------------------- the test


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> pathlib.Path:
    """A generated 64x48 sequence of 3 frames (TUM layout, depth, exposure paths, camera.yaml)."""
    from mbavo_jax.config import SynthConfig
    from mbavo_jax.synthetic import generate_sequence

    out = tmp_path_factory.mktemp("bad_input") / "seq"
    generate_sequence(SynthConfig(frames=3, width=64, height=48), out, progress=False)
    return out


def snapshot(root: pathlib.Path) -> dict[str, tuple[int, int]]:
    """Every path under ``root`` with its size and modification time."""
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id) for c in CASES])
def test_bad_input_is_one_line_and_writes_nothing(case: Case, sequence, tmp_path, mbavo):
    seq = shutil.copytree(sequence, tmp_path / "seq")
    (tmp_path / "file").write_text("a regular file\n")
    if case.setup is not None:
        case.setup(seq)
    fill = lambda text: text.format(seq=seq, tmp=tmp_path, file=tmp_path / "file")
    before = snapshot(tmp_path)
    r = mbavo(*map(fill, case.argv))
    lines = r.stderr.splitlines()
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert len(lines) == 1 and lines[0].startswith("mbavo: error: "), r.stderr
    assert fill(case.expect) in lines[0], (fill(case.expect), lines[0])
    assert "Traceback" not in r.stderr and "np.float64" not in r.stderr, r.stderr
    assert r.stdout == "", r.stdout
    assert snapshot(tmp_path) == before, "a failed command created or changed files"


def test_frame_index_out_of_range_is_an_index_error_naming_the_sequence(sequence):
    from mbavo_jax.datasets import open_sequence

    seq = open_sequence(sequence)
    for i in (3, -4, 100):
        with pytest.raises(FrameIndexError, match=f"frame {i} out of range") as info:
            seq[i]
        assert isinstance(info.value, IndexError) and isinstance(info.value, MbavoError)
    assert [f.index for f in seq] == [0, 1, 2] and seq[-1].index == 2


@pytest.mark.parametrize("values, expect", [
    (dict(levels=0), "tracker.levels: must be >= 1, got 0"),
    (dict(levels=-1), "tracker.levels: must be >= 1, got -1"),
    # levels=2.5: the test session's type-checking hook refuses it before the dataclass does (the
    # --set row track_set_tracker.levels=2.5 covers it)
    (dict(huber=-1.0), "tracker.huber: must be > 0, got -1.0"),
    (dict(huber=float("nan")), "tracker.huber: must be > 0, got nan"),
    (dict(points=(0, 0, 0, 0)), "tracker.points: must be >= 1"),
    (dict(cell=(0, 0, 0, 0)), "tracker.cell: must be >= 1"),
    (dict(max_steps=(0, 1, 1, 1)), "tracker.max_steps: must be >= 1"),
    (dict(rtol=float("nan")), "tracker.rtol: must be > 0, got nan"),
    (dict(atol=float("nan")), "tracker.atol: must be > 0, got nan"),
], ids=lambda v: str(v) if isinstance(v, str) else "-".join(f"{k}={x}" for k, x in v.items()))
def test_tracker_settings_built_in_python_are_checked_too(values, expect):
    """The API's TrackerConfig checks the same ranges as the files and --set (one ConfigError line)."""
    from mbavo_jax.config import TrackerConfig
    from mbavo_jax.errors import ConfigError

    with pytest.raises(ConfigError) as info:
        TrackerConfig(**values)
    assert expect in str(info.value) and "\n" not in str(info.value)
