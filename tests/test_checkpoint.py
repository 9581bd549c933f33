"""The monocular run's --resume checkpoint is plain data (``checkpoint.npz``: arrays and a JSON
header, ``odometry.checkpoint``): a crafted pickle runs nothing (an old ``checkpoint.pkl`` is
refused unread, one line, exit 1), a hostile archive (an unknown type, a field more or less,
shapes and dtypes that differ from the header's or from the fields' annotations, a pickle inside,
an archive cut short) is one line, and a real monocular state comes back equal leaf by leaf."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pickle
import shlex
import typing
import zipfile

import jax
import numpy as np
import pytest

from mbavo_jax.config import MonoConfig, RunConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import DataError
from mbavo_jax.geometry import PinholeCamera, Pose
from mbavo_jax.mono.candidates import Candidates
from mbavo_jax.mono.init import TwoViewTracker
from mbavo_jax.mono.motions import Motion, Motions, PoseAt
from mbavo_jax.mono.window import Window
from mbavo_jax.odometry import run_odometry
from mbavo_jax.odometry.checkpoint import STATE_TYPES
from mbavo_jax.odometry.exposure import ExposureEstimate, RawFrame
from mbavo_jax.odometry.folder import Checkpoint, read_checkpoint, write_checkpoint
from mbavo_jax.odometry.mono import MonoState
from mbavo_jax.odometry.state import Fit, KeyframeState, PendingDeblur, RunState
from mbavo_jax.synthetic import PRESETS, SynthConfig, generate_sequence
from mbavo_jax.tracking import Keyframe
from mbavo_jax.tracking.points import LevelPoints

W, H = 160, 120
RESUME = "cannot --resume (run without --resume to start afresh)"


class Payload:
    """What a hostile pickle holds: unpickling it runs a shell command that makes ``marker``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, ("touch " + shlex.quote(str(self.marker)),)


def assert_same(a, b, where: str = "state") -> None:
    """``a`` and ``b`` equal leaf by leaf: the same types, array kinds, dtypes, shapes and bits."""
    assert type(a) is type(b), f"{where}: {type(a)} != {type(b)}"
    if isinstance(a, (np.ndarray, np.generic, jax.Array)):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes(), where
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"


@pytest.fixture(scope="module")
def state() -> RunState:
    """A hand-made state holding every kind of value a monocular run's does (the initialiser and a
    window at once; one image shared by three fields; a NumPy scalar; -inf)."""
    rng = np.random.default_rng(0)
    image = rng.random((H, W)).astype(np.float32)
    depth = np.full((H, W), 2.0, np.float32)
    camera = PinholeCamera.create(150.0, 150.0, 79.5, 59.5, W, H)
    pose = Pose.identity()
    candidates = Candidates.create(rng.random((4, 2)).astype(np.float32), np.ones(4, bool))
    mono = MonoState(initialiser=TwoViewTracker.start(image, camera, MonoConfig()), reference=(0.25, image), tries=1,
                     motions=Motions(items=(Motion(pose, 0.1),)), lost=PoseAt(0.5, pose), window=Window.empty(2, 8, H, W),
                     slots=(1,), stamps=(0.5,), candidates=(None, candidates), last_stamp=0.5, frame_dt=0.1)
    raw = RawFrame(0.5, image, None, pose, pose, 0.1, 12.5)
    return RunState(keyframe=KeyframeState(Keyframe.create(image, depth, camera), pose, 0.5), mids=((0.5, pose),),
                    pending=PendingDeblur(image, depth, None), tracked=3, exposure=ExposureEstimate(0.5, 8, ((0.01, 1.0, 0.1),)),
                    recent=(raw,), fits=(Fit(0.01, None), Fit(np.float64(0.02), 1.5)), backend=mono)


@pytest.fixture
def saved(state, tmp_path):
    """A run folder holding ``state``'s checkpoint (frame 7, 42 points)."""
    write_checkpoint(tmp_path, Checkpoint(7, state, 42))
    return tmp_path


def test_a_state_comes_back_equal_leaf_by_leaf_from_plain_data(state, saved):
    assert not (saved / "checkpoint.pkl").exists()
    with zipfile.ZipFile(saved / "checkpoint.npz") as archive:  # .npy entries and a JSON header, nothing else
        assert all(n.endswith(".npy") for n in archive.namelist())
    with np.load(saved / "checkpoint.npz", allow_pickle=False) as npz:
        header = json.loads(npz["header"].tobytes())
        assert all(npz[k].dtype != object for k in npz.files)
    assert header["format"] == "mbavo-checkpoint" and header["version"] == 1 and header["state"]["type"] == "RunState"
    back = read_checkpoint(saved)
    assert (back.index, back.points) == (7, 42)
    assert_same(state, back.state)
    assert back.state.pending.image is back.state.backend.reference[1] is back.state.recent[0].image  # stored once, one array


def test_the_registry_holds_every_type_a_run_state_names():
    """Every dataclass a RunState's annotations reach (and those behind its ``object``, ``Any`` and
    bare ``tuple`` fields) can be written and read back."""

    def named(hint):
        if dataclasses.is_dataclass(hint):
            yield hint
        for arg in typing.get_args(hint):
            yield from named(arg)

    seen, todo = set(), [RunState, MonoState, TwoViewTracker, Candidates, Keyframe, LevelPoints, PinholeCamera]
    while todo:
        cls = todo.pop()
        if cls not in seen:
            seen.add(cls)
            todo += [t for hint in typing.get_type_hints(cls).values() for t in named(hint)]
    assert seen <= set(STATE_TYPES.values()), seen - set(STATE_TYPES.values())


# ---------------------------------------------------------------------------------------- hostile files


def node(header: dict, name: str, nth: int = 0) -> dict:
    """The header's ``nth`` object of type ``name`` (depth first)."""
    found = []

    def walk(x):
        if isinstance(x, dict):
            if x.get("type") == name:
                found.append(x)
            for v in x.values():
                walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)

    walk(header["state"])
    return found[nth]


def rewrite(folder, edit, compressed: bool = False) -> None:
    """The folder's checkpoint written again after ``edit(header, entries)`` (both changed in place)."""
    path = folder / "checkpoint.npz"
    with np.load(path, allow_pickle=False) as npz:
        entries = {k: npz[k] for k in npz.files}
    header = json.loads(entries.pop("header").tobytes())
    edit(header, entries)
    text = np.frombuffer(json.dumps(header).encode(), np.uint8)
    with open(path, "wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, header=text, **entries)


def change_array(type_name: str, field: str, new, header_too: bool = True):
    """An edit that replaces the array of ``type_name.field`` by ``new(old)`` (its header entry too, or not)."""

    def edit(header, entries):
        spec = node(header, type_name)["fields"][field]
        entries[spec["array"]] = value = new(entries[spec["array"]])
        if header_too:
            spec.update(dtype=value.dtype.name, shape=list(value.shape))

    return edit


def set_field(type_name: str, field: str, value):
    def edit(header, entries):
        node(header, type_name)["fields"][field] = value

    return edit


def extra_field(header, entries):
    node(header, "RunState")["fields"]["hook"] = 1


def missing_field(header, entries):
    del node(header, "RunState")["fields"]["tracked"]


def unknown_type(name):
    def edit(header, entries):
        node(header, "Fit")["type"] = name

    return edit


def pickle_inside(marker):
    """An entry that holds a pickled object (the header still says float32)."""

    def edit(header, entries):
        entries[node(header, "Window")["fields"]["affine"]["array"]] = np.array([Payload(marker)], dtype=object)

    return edit


def deep(header, entries):
    nested = 0
    for _ in range(200):
        nested = {"tuple": [nested]}
    header["state"] = nested


def other_version(header, entries):
    header["version"] = 2


def unreferenced(header, entries):
    entries["a9999"] = np.zeros(3, np.float32)


def keyframe_level(header, entries):
    spec = node(header, "Keyframe")["fields"]["images"]["tuple"][1]
    entries[spec["array"]] = value = np.zeros((7, 9), np.float32)
    spec.update(shape=list(value.shape))


HOSTILE = {
    "an_unknown_type": (unknown_type("Popen"), "'Popen', which is no part of a run's state"),
    "a_dotted_type_name": (unknown_type("subprocess.Popen"), "which is no part of a run's state"),
    "a_type_name_that_forges_a_second_line": (unknown_type("Fit\nmbavo: error: forged"), "'Fit\\nmbavo: error: forged'"),
    "a_field_more": (extra_field, "RunState with the fields"),
    "a_field_less": (missing_field, "RunState with the fields"),
    "an_entry_of_another_shape_than_its_header": (change_array("Window", "images", lambda a: np.zeros((2, H, W + 1), a.dtype), False),
                                                  "the header says float32 (2, 120, 160)"),
    "an_entry_of_another_dtype_than_its_header": (change_array("Window", "images", lambda a: a.astype(np.float64), False),
                                                  "holds float64"),
    "sizes_that_disagree_within_an_object": (change_array("Window", "kf_valid", lambda a: np.zeros(3, bool)),
                                             "Window.kf_valid does not fit its type"),
    "flags_stored_as_ints": (change_array("Window", "kf_valid", lambda a: a.astype(np.int32)), "Window.kf_valid does not fit"),
    "a_float64_jax_array_where_jax_runs_32_bit": (change_array("Window", "images", lambda a: a.astype(np.float64)), "JAX_ENABLE_X64"),
    "an_image_size_other_than_the_keyframe's": (change_array("Window", "images", lambda a: np.zeros((2, H, W + 2), a.dtype)),
                                                "image sizes disagree"),
    "a_pyramid_level_of_another_size": (keyframe_level, "Keyframe: a pyramid level"),
    "a_string_where_a_count_is": (set_field("RunState", "tracked", "3"), "RunState.tracked does not fit its type"),
    "a_back_end_of_another_type": (set_field("RunState", "backend", {"type": "Fit", "fields": {"rms": 1.0, "jump_px": None}}),
                                   "its back-end is not a monocular state"),
    "window_slots_outside_the_window": (set_field("MonoState", "slots", {"tuple": [5]}), "do not fit a window of 2 keyframes"),
    "values_nested_too_deeply": (deep, "nested too deeply"),
    "another_version": (other_version, "a checkpoint of another version (2; this program reads 1)"),
    "an_entry_no_value_refers_to": (unreferenced, "entries that no value refers to"),
}


def assert_refused(folder, *fragments) -> str:
    with pytest.raises(DataError) as info:
        read_checkpoint(folder)
    message = str(info.value)
    assert len(message.splitlines()) == 1 and message.endswith(RESUME), message
    assert all(f in message for f in fragments), message
    return message


@pytest.mark.parametrize("case", list(HOSTILE))
def test_a_hostile_archive_is_one_line(case, saved):
    edit, fragment = HOSTILE[case]
    rewrite(saved, edit)
    assert_refused(saved, "checkpoint.npz: ", fragment)


def test_a_pickle_inside_the_archive_is_never_unpickled(saved):
    marker = saved / "MARKER"
    rewrite(saved, pickle_inside(marker))
    assert_refused(saved, "holds object")
    assert not marker.exists()


def test_a_compressed_archive_is_refused(saved):
    rewrite(saved, lambda header, entries: None, compressed=True)
    assert_refused(saved, "is compressed")


def _zip_of_garbage() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("header.npy", os.urandom(300))
    return buffer.getvalue()


def _npy() -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.zeros(3))
    return buffer.getvalue()


@pytest.mark.parametrize("content", ["pickle", "text", "zip_of_garbage", "npy", "cut_short", "empty"])
def test_a_file_that_is_no_archive_is_one_line(content, saved, tmp_path):
    path, marker = saved / "checkpoint.npz", tmp_path / "MARKER"
    data = {"pickle": lambda: pickle.dumps(Checkpoint(0, Payload(marker))), "text": lambda: b"not a checkpoint",
            "zip_of_garbage": _zip_of_garbage, "npy": _npy, "cut_short": lambda: path.read_bytes()[: path.stat().st_size // 2],
            "empty": lambda: b""}[content]()
    path.write_bytes(data)
    assert_refused(saved, "checkpoint.npz: unreadable")
    assert not marker.exists()


# ------------------------------------------------------------------------------- a real monocular run


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    """A blurred 160x120 sequence of 10 frames (strong preset) without exposure metadata."""
    out = tmp_path_factory.mktemp("checkpoint") / "strong"
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": 10, "width": W, "height": H, "subframes": 8, "seed": 1,
                         "real_textures": False, "exposure_info": False})
    generate_sequence(cfg, out, progress=False)
    return out


def test_an_old_pickled_checkpoint_is_refused_unread(seq_dir, tmp_path, mbavo):
    """``mbavo track --resume`` in a folder whose checkpoint.pkl runs a command when unpickled:
    one line, exit 1, and the command never ran."""
    out, marker = tmp_path / "run", tmp_path / "MARKER"
    out.mkdir()
    (out / "frames.csv").write_text("index,timestamp,status\n0,0.000000,initialising\n")
    (out / "checkpoint.pkl").write_bytes(pickle.dumps(Payload(marker)))
    r = mbavo("track", seq_dir, "--out", out, "--mode", "mono", "--resume", "-q")
    assert not marker.exists(), "the pickle was loaded: its command ran"
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "checkpoint.pkl" in r.stderr and "never read" in r.stderr and RESUME in r.stderr, r.stderr


@pytest.mark.slow
def test_a_real_monocular_state_comes_back_equal_leaf_by_leaf(seq_dir, tmp_path):
    """Every state of a short monocular run (initialising, then with a window), written and read
    back; the run's own last checkpoint equals its last state."""
    states = []
    config = RunConfig().replace(odometry=dict(mode="mono"), mono=dict(exposure_probe=0))
    run_odometry(open_sequence(seq_dir), tmp_path / "run", config, progress=False,
                 observer=lambda frame, before, outcome, after: states.append(after))
    assert states[0].backend.initialiser is not None and states[-1].backend.window is not None, "the run never initialised"
    assert_same(states[-1], read_checkpoint(tmp_path / "run").state)
    for k, state in enumerate(states):
        write_checkpoint(tmp_path, Checkpoint(k, state, 0))
        assert_same(state, read_checkpoint(tmp_path).state, f"frame {k}")
