"""The checkpoint a monocular run leaves for ``--resume``, as plain data: a NumPy ``.npz`` archive
of the state's arrays and a JSON header (the archive's ``header`` entry, UTF-8 bytes) that
describes the structure around them.

The header holds the format and version, the checkpoint's frame index and point count, and the
state: Python numbers, strings, None and tuples as themselves, each array as a reference to its
archive entry with its kind (NumPy, JAX, NumPy scalar), dtype and shape, and each object as the
name of one of :data:`STATE_TYPES` (this program's own state classes) with its fields. Reading
never unpickles (``allow_pickle=False``) and never imports or calls anything the file names: the
objects are made from the registry and filled field by field, and a file that does not describe a
run's state exactly (a type outside the registry, a field more or less, a value that does not fit
its field's annotation (array dtypes, ranks and the sizes named in them, one object at a time), an
entry whose dtype or shape differs from the header's, image sizes that disagree, an archive cut
short) is refused as one line (``DataError``) with nothing run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import pathlib
import re
import types
import typing
import zipfile

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
from jaxtyping import Array, Float

from ..config import MonoConfig, Settings
from ..errors import DataError
from ..geometry import ExposureTrajectory, PinholeCamera, Pose
from ..geometry.spline import SplineTrajectory
from ..mono.candidates import Candidates
from ..mono.direct_init import Alignment, DirectInitializer, Reference
from ..mono.init import Tracks, TwoViewTracker
from ..mono.motions import Motion, Motions, PoseAt
from ..mono.window import Prior, Window
from ..tracking import Keyframe
from ..tracking.points import LevelPoints
from .exposure import ExposureEstimate, RawFrame
from .mono import MonoState
from .state import Fit, KeyframeState, PendingDeblur, RunState

__all__ = ["FORMAT", "VERSION", "STATE_TYPES", "Checkpoint", "save_checkpoint", "load_checkpoint"]

FORMAT, VERSION = "mbavo-checkpoint", 1
STATE_TYPES = {cls.__name__: cls for cls in (
    RunState, KeyframeState, PendingDeblur, Fit, ExposureEstimate, RawFrame, MonoState, Motions, Motion, PoseAt, TwoViewTracker,
    DirectInitializer, Reference, Alignment,
    Tracks, MonoConfig, Window, Prior, Candidates, Keyframe, LevelPoints, Pose, ExposureTrajectory, SplineTrajectory, PinholeCamera)}
DTYPES = frozenset({"bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64", "float16", "float32", "float64"})
KINDS = ("numpy", "jax", "scalar")
MAX_DEPTH = 64  # nesting of the header's values (a run's state nests about ten deep)
ENTRY = re.compile(r"(header|a\d{1,7})\.npy")


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A pipeline's state (a ``RunState``) after frame ``index`` was committed, with the vertices
    points.ply had then (``points``); the triptychs drawn are the state's own count."""

    index: int
    state: object
    points: int = 0


class Invalid(Exception):
    """Why a file is not a checkpoint this program reads (the reader's message, without the file)."""


# ------------------------------------------------------------------------------------------ writing


class _Encoder:
    """The header's description of a value; its arrays collected in ``arrays`` (an array met twice
    is stored once, and read back as one array)."""

    def __init__(self):
        self.arrays: dict[str, np.ndarray] = {}
        self._keys: dict[int, str] = {}

    def __call__(self, x):
        if isinstance(x, (np.ndarray, np.generic, jax.Array)):
            return self._array(x)
        if x is None or type(x) in (bool, int, str):
            return x
        if type(x) is float:
            return x if math.isfinite(x) else {"float": repr(x)}
        if type(x) is tuple:
            return {"tuple": [self(v) for v in x]}
        if STATE_TYPES.get(type(x).__name__) is type(x):
            return {"type": type(x).__name__, "fields": {f.name: self(getattr(x, f.name)) for f in dataclasses.fields(x)}}
        raise TypeError(f"a checkpoint cannot hold a {type(x).__module__}.{type(x).__qualname__}")

    def _array(self, x) -> dict:
        kind = "jax" if isinstance(x, jax.Array) else "scalar" if isinstance(x, np.generic) else "numpy"
        key = self._keys.get(id(x))
        if key is None:
            key = self._keys[id(x)] = f"a{len(self.arrays)}"
            self.arrays[key] = np.asarray(x)
            if self.arrays[key].dtype.name not in DTYPES:
                raise TypeError(f"a checkpoint cannot hold an array of {self.arrays[key].dtype}")
        a = self.arrays[key]
        return {"array": key, "kind": kind, "dtype": a.dtype.name, "shape": list(a.shape)}


def save_checkpoint(path: pathlib.Path, checkpoint: Checkpoint) -> None:
    """``checkpoint`` written to ``path`` (an .npz archive), replacing the previous one in one step."""
    encode = _Encoder()
    header = {"format": FORMAT, "version": VERSION, "index": int(checkpoint.index), "points": int(checkpoint.points),
              "state": encode(checkpoint.state)}
    text = json.dumps(header, allow_nan=False, separators=(",", ":")).encode()
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, header=np.frombuffer(text, np.uint8), **encode.arrays)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------ reading


def _entries(archive: zipfile.ZipFile) -> dict[str, zipfile.ZipInfo]:
    """The archive's entries by name (``header``, ``a0``, ...): stored uncompressed, as ``save_checkpoint`` writes them."""
    entries = {}
    for info in archive.infolist():
        if not ENTRY.fullmatch(info.filename) or info.filename[:-4] in entries:
            raise Invalid(f"unreadable (an entry {info.filename[:40]!r}, which a checkpoint does not hold)")
        if info.compress_type != zipfile.ZIP_STORED:
            raise Invalid(f"unreadable (entry {info.filename!r} is compressed; a checkpoint's are stored)")
        entries[info.filename[:-4]] = info
    if "header" not in entries:
        raise Invalid("unreadable (no header: not a checkpoint of this program)")
    return entries


def _read_entry(archive: zipfile.ZipFile, info: zipfile.ZipInfo, dtype: str | None = None, shape: tuple | None = None) -> np.ndarray:
    """The array in entry ``info``, once its .npy header says a plain dtype (``dtype`` and ``shape``
    when given) and the entry holds exactly their bytes (nothing is allocated for an array it does not hold)."""
    with archive.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version not in ((1, 0), (2, 0)):
            raise Invalid(f"unreadable (entry {info.filename!r} is a .npy file of version {version})")
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        found, _, found_dtype = read_header(fh)
        plain = not found_dtype.hasobject and found_dtype.isnative and found_dtype.name in DTYPES
        if not plain or (dtype is not None and (found_dtype.name != dtype or found != shape)):
            raise Invalid(f"entry {info.filename!r} holds {found_dtype} {found}, the header says {dtype} {shape}")
        if fh.tell() + math.prod(found) * found_dtype.itemsize != info.file_size:
            raise Invalid(f"unreadable (entry {info.filename!r} is cut short or too long)")
    with archive.open(info) as fh:
        return np.lib.format.read_array(fh, allow_pickle=False)


def _header(archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> dict:
    """The archive's JSON header, of this format and version."""
    text = _read_entry(archive, info)
    header = json.loads(text.tobytes().decode("utf-8"), parse_constant=_float) if text.dtype == np.uint8 and text.ndim == 1 else None
    if type(header) is not dict or header.get("format") != FORMAT:
        raise Invalid("not a checkpoint of this program")
    if type(header.get("version")) is not int or header["version"] != VERSION:
        raise Invalid(f"a checkpoint of another version ({_short(header.get('version'))}; this program reads {VERSION})")
    if set(header) != {"format", "version", "index", "points", "state"}:
        raise Invalid(f"a header with the keys {sorted(header)[:8]}")
    return header


def _short(value, length: int = 40) -> str:
    """``value`` as the header has it, on one line, at most ``length`` characters."""
    return repr(value)[:length]


def _float(text) -> float:
    if text not in ("inf", "-inf", "nan"):
        raise Invalid(f"a number {_short(text)} that is not one")
    return float(text)


def _shape(shape) -> tuple[int, ...]:
    if type(shape) is not list or not all(type(n) is int and n >= 0 for n in shape) or len(shape) > 8:
        raise Invalid(f"an array shape {_short(shape)} that is not one")
    return tuple(shape)


class _Decoder:
    """The values a header describes, its arrays read from ``archive`` (each entry once, shared
    where the header refers to it twice), its objects made from :data:`STATE_TYPES` only."""

    def __init__(self, archive: zipfile.ZipFile, entries: dict[str, zipfile.ZipInfo]):
        self.archive, self.entries = archive, entries
        self.read: dict[str, tuple] = {}  # entry -> (its description, the value)

    def __call__(self, node, depth: int = 0):
        if depth > MAX_DEPTH:
            raise Invalid("values nested too deeply for a run's state")
        if node is None or type(node) in (bool, int, float, str):
            return node
        keys = set(node) if type(node) is dict else None
        if keys == {"float"}:
            return _float(node["float"])
        if keys == {"tuple"} and type(node["tuple"]) is list:
            return tuple(self(v, depth + 1) for v in node["tuple"])
        if keys == {"array", "kind", "dtype", "shape"}:
            return self._array(node)
        if keys == {"type", "fields"}:
            return self._object(node, depth)
        raise Invalid(f"a value the header cannot describe ({json.dumps(node)[:60]})")

    def _array(self, node: dict):
        key, kind, dtype, shape = node["array"], node["kind"], node["dtype"], _shape(node["shape"])
        if type(key) is not str or key == "header" or key not in self.entries:
            raise Invalid(f"an array {_short(key)} that the archive does not hold")
        if kind not in KINDS or dtype not in DTYPES or (kind == "scalar" and shape):
            raise Invalid(f"array {key}: a {_short(kind)} of {_short(dtype)}, which a checkpoint does not hold")
        if key in self.read:
            if self.read[key][0] != (kind, dtype, shape):
                raise Invalid(f"array {key} described twice, differently")
            return self.read[key][1]
        array = _read_entry(self.archive, self.entries[key], dtype, shape)
        value = array[()] if kind == "scalar" else jnp.asarray(array) if kind == "jax" else array
        if kind == "jax" and value.dtype != array.dtype:
            raise Invalid(f"array {key} is a {dtype} JAX array, which JAX here makes {value.dtype} (JAX_ENABLE_X64)")
        self.read[key] = ((kind, dtype, shape), value)
        return value

    def _object(self, node: dict, depth: int):
        name, fields = node["type"], node["fields"]
        cls = STATE_TYPES.get(name) if type(name) is str else None
        if cls is None:
            raise Invalid(f"a type {_short(name)}, which is no part of a run's state")
        names = [f.name for f in dataclasses.fields(cls)]
        if type(fields) is not dict or set(fields) != set(names):
            given = sorted(fields) if type(fields) is dict else fields
            raise Invalid(f"{name} with the fields {_short(given, 80)}, where this program's are {names}")
        values = {k: self(fields[k], depth + 1) for k in names}
        wrong = _misfit(cls, values)
        if wrong is not None:
            raise Invalid(f"{name}.{wrong} does not fit its type ({_hints(cls)[wrong]})")
        obj = _made(cls, values)
        problem = CHECKS[cls](obj) if cls in CHECKS else None
        if problem:
            raise Invalid(f"{name}: {problem}")
        return obj


def _made(cls: type, values: dict):
    """An instance of ``cls`` holding ``values``: filled field by field as unpickling does (no
    ``__init__``: the values are the ones the run had), but settings, which check their ranges."""
    if issubclass(cls, Settings):
        try:
            return cls(**values)
        except Exception as exc:  # ConfigError: a value out of its range
            raise Invalid(f"{cls.__name__}: {exc}") from None
    obj = object.__new__(cls)
    for name, value in values.items():
        object.__setattr__(obj, name, value)
    return obj


@functools.cache
def _hints(cls: type) -> dict:
    return typing.get_type_hints(cls)


def _misfit(cls: type, values: dict) -> str | None:
    """The first field of ``values`` that does not fit ``cls``'s annotation, or whose arrays give a
    named dimension (``K`` of ``Float[Array, "K 2"]``) another size than the fields before it did; None."""
    hints, bound = _hints(cls), {}
    for name, value in values.items():
        sizes: list[tuple[str, int]] = []
        if not _fits(value, hints[name], sizes) or any(bound.setdefault(n, k) != k for n, k in sizes):
            return name
    return None


def _named_sizes(dims: str, shape: tuple) -> list[tuple[str, int]]:
    """(name, size) of each named dimension of a jaxtyping annotation's ``dims`` ("K H W", "... 4") in ``shape``."""
    names = dims.split()
    if "..." in names:
        names = names[names.index("...") + 1:]
        shape = shape[len(shape) - len(names):] if names else ()
    return [(n, k) for n, k in zip(names, shape) if n.isidentifier() and n != "_"]


def _fits(value, hint, sizes: list) -> bool:
    """Whether ``value`` fits the annotation ``hint`` (ints where floats are expected, NumPy scalars
    as Python's); the sizes its arrays give named dimensions are added to ``sizes``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is typing.Any or hint is object:
        return True
    if hint is None or hint is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a, sizes) for a in args)
    if hint is tuple or origin is tuple:
        if type(value) is not tuple:
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0], sizes) for v in value)
        return not args or (len(value) == len(args) and all(_fits(v, a, sizes) for v, a in zip(value, args)))
    if hint in (bool, int, float):
        ok = {bool: (bool, np.bool_), int: (int, np.integer), float: (int, float, np.integer, np.floating)}[hint]
        return isinstance(value, ok) and (hint is bool or not isinstance(value, (bool, np.bool_)))
    if isinstance(hint, type) and issubclass(hint, jaxtyping.AbstractArray):  # dtype and rank; the sizes are compared by _misfit
        ok = isinstance(value, hint)
        sizes += _named_sizes(hint.dim_str, value.shape) if ok else []
        return ok
    return isinstance(hint, type) and isinstance(value, hint)


# ----------------------------------------------------------------------- what annotations do not say


def _run_state(state: RunState) -> str | None:
    if not (state.backend is None or isinstance(state.backend, MonoState)):
        return "its back-end is not a monocular state"
    sizes = {s for s in _image_sizes(state) if s is not None}
    return f"image sizes disagree ({sorted(sizes)})" if len(sizes) > 1 else None


def _image_sizes(state: RunState):
    """(height, width) of every full-resolution image and camera the state holds."""
    shape = lambda a: None if a is None else tuple(np.shape(a))
    if state.keyframe is not None:
        kf = state.keyframe.keyframe
        yield from (shape(kf.images[0]), shape(kf.depth), (kf.cameras[0].height, kf.cameras[0].width))
    if state.pending is not None:
        yield from (shape(state.pending.image), shape(state.pending.depth))
    for raw in state.recent:
        yield from (shape(raw.image), shape(raw.depth))
    mono = state.backend
    if mono is not None and mono.window is not None:
        yield from (mono.window.images.shape[1:], mono.window.raw.shape[1:] if mono.window.raw.size else None)
    if mono is not None and mono.reference is not None:
        yield shape(mono.reference[1])
    if mono is not None and mono.initialiser is not None:
        tracker = mono.initialiser
        yield from ((tracker.camera.height, tracker.camera.width), shape(tracker.tracks.ref_image), shape(tracker.tracks.last))


def _mono_state(mono: MonoState) -> str | None:
    if not (mono.initialiser is None or isinstance(mono.initialiser, TwoViewTracker)):
        return "its initialiser is not a two-view tracker"
    if mono.reference is not None and np.ndim(mono.reference[1]) != 2:
        return "its reference frame is not an image"
    if len(mono.stamps) != len(mono.slots) or len(set(mono.slots)) != len(mono.slots):
        return "its window slots and their stamps disagree"
    if mono.window is None:
        return None if not mono.slots and not mono.candidates else "window slots without a window"
    k = mono.window.slots
    if len(mono.candidates) != k or any(not 0 <= s < k for s in mono.slots):
        return f"its window slots or candidates do not fit a window of {k} keyframes"
    if not all(c is None or isinstance(c, Candidates) for c in mono.candidates):
        return "its candidates are not candidate points"
    return None


def _keyframe(kf: Keyframe) -> str | None:
    """Per pyramid level: an image the size of its camera, its points and depth points."""
    levels = len(kf.images)
    if not levels or not len(kf.cameras) == len(kf.points) == len(kf.depth_points) == levels:
        return "its pyramid levels disagree"
    for image, camera, points, grid in zip(kf.images, kf.cameras, kf.points, kf.depth_points):
        if not (isinstance(image, Float[Array, "_ _"]) and isinstance(camera, PinholeCamera)
                and image.shape == (camera.height, camera.width) and isinstance(points, LevelPoints) and isinstance(grid, LevelPoints)):
            return "a pyramid level that is not an image of its camera's size with its points"
    return None if np.shape(kf.depth) == kf.images[0].shape else "its depth map is not the size of its image"


def _level_points(points: LevelPoints) -> str | None:
    n = len(points.valid) if np.ndim(points.valid) == 1 else -1
    ok = (points.valid.dtype == bool and points.pixels.shape == (n, 2) and points.depths.shape == (n,)
          and points.pixels.dtype.kind == "f" and points.depths.dtype.kind == "f")
    return None if ok else "not N pixels (N, 2), depths (N,) and flags (N,)"


CHECKS = {RunState: _run_state, MonoState: _mono_state, Keyframe: _keyframe, LevelPoints: _level_points}


def _decoded(archive: zipfile.ZipFile) -> Checkpoint:
    """The checkpoint an open archive holds."""
    entries = _entries(archive)
    header = _header(archive, entries["header"])
    index, points = header["index"], header["points"]
    if type(index) is not int or type(points) is not int or index < 0 or points < 0:
        raise Invalid("a frame index or point count that is not a count")
    decode = _Decoder(archive, entries)
    state = decode(header["state"])
    if type(state) is not RunState:
        raise Invalid("its state is not a run's state")
    if set(decode.read) != set(entries) - {"header"}:
        raise Invalid("unreadable (entries that no value refers to)")
    return Checkpoint(index, state, points)


def load_checkpoint(path: pathlib.Path) -> Checkpoint:
    """The :class:`Checkpoint` in ``path``; a file that is not one exactly is a one-line ``DataError``."""
    resume = "cannot --resume (run without --resume to start afresh)"
    try:
        with zipfile.ZipFile(path) as archive:
            return _decoded(archive)
    except Invalid as exc:
        raise DataError(path, f"{exc}: {resume}") from None
    except Exception as exc:  # not an archive, cut short, a header that is not JSON, ...
        raise DataError(path, f"unreadable ({type(exc).__name__}): {resume}") from None
