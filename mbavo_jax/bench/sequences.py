"""The benchmarks' data: generated sequences of the blur presets (made once, under ``runs/``), their
copies with the exposure metadata hidden, the real clips of the shared data folder, the blurred TUM
clip, and the tracking benchmark's frame pairs."""

from __future__ import annotations

import dataclasses
import pathlib
import re

import jax.numpy as jnp
import numpy as np

from ..config import PRESETS, BenchConfig, OdometryConfig, SynthConfig
from ..datasets import open_sequence
from ..errors import MbavoError
from ..geometry import ExposureTrajectory, Pose
from ..io import read_image_gray
from ..synthetic.scene import SCENES
from ..tracking import constant_velocity_guess

__all__ = ["bench_data", "scene_settings", "SCENE_FORM", "with_hidden_exposure", "real_clip", "tum_blurred", "tracking_pairs",
           "Generated", "generated_sequences", "make_generated"]


def _P(v):
    return Pose.from_vector(jnp.asarray(v, jnp.float32))


def tracking_pairs(seq, frames: int):
    """(index, sharp keyframe, its depth, next frame, constant-velocity guess, true path) per pair; the
    guess's exposure is the recorded one, or without metadata ``odometry.exposure_guess`` of the interval."""
    _, mids = seq.groundtruth
    _, S, E = seq.exposure_paths
    dt = float(np.median(np.diff(seq.timestamps)))
    tau = float(seq.exposures[0]) if seq.exposures is not None else OdometryConfig().exposure_guess * dt
    for k in range(1, min(len(seq) - 1, frames + 1)):
        sharp_path = pathlib.Path(seq[k].path).parent.parent / "sharp" / pathlib.Path(seq[k].path).name
        T_w_ref = _P(mids[k])
        init = constant_velocity_guess(T_w_ref, _P(mids[k - 1]), _P(mids[k]), dt, tau)
        gt = ExposureTrajectory(T_w_ref.inverse().compose(_P(S[k + 1])), T_w_ref.inverse().compose(_P(E[k + 1])))
        yield k, read_image_gray(sharp_path), seq[k].depth, seq[k + 1], init, gt


SCENE_SEQUENCE = re.compile(r"(?P<scene>[a-z]+?)(?P<photo>_photo)?_b(?P<blur>\d+(?:\.\d+)?)(?:_(?P<motion>[a-z]+))?")
SCENE_FORM = "<scene>[_photo]_b<px>[_<preset>], e.g. plane_b10, plane_photo_b20_extreme"


def scene_settings(name: str) -> dict | None:
    """The generator settings a named scene sequence ``<scene>[_photo]_b<px>[_<preset>]`` stands
    for: the scene, dead-leaves textures with ``_photo``, a preset's motion (strong unless named)
    and the exposure fitted to a mean blur of px pixels (``SynthConfig.blur_px``; b0: sharp, as the
    none preset). None when ``name`` has not that form; MbavoError for an unknown scene or preset."""
    match = SCENE_SEQUENCE.fullmatch(name)
    if match is None:
        return None
    scene, motion, blur = match["scene"], match["motion"] or "strong", float(match["blur"])
    if scene not in SCENES or motion not in PRESETS:
        raise MbavoError(f"sequence '{name}': unknown scene or motion preset (scenes: {', '.join(SCENES)}; presets: {', '.join(PRESETS)})")
    sharp = dict(exposure_ms=0.0, subframes=1) if blur == 0 else dict(blur_px=blur, exposure_ms=PRESETS[motion]["exposure_ms"] or 20.0,
                                                                     subframes=SynthConfig().subframes)
    return {**PRESETS[motion], **sharp, "scene": scene, "texture": "photo" if match["photo"] else "mixed"}


def _synth_settings(preset: str, scene: str) -> dict:
    """A blur preset's settings in ``scene``, or a named scene sequence's (:func:`scene_settings`)."""
    if preset in PRESETS:
        return {**PRESETS[preset], "scene": scene}
    named = scene_settings(preset)
    if named is None:
        raise MbavoError(f"unknown blur preset '{preset}' (choose from {', '.join(PRESETS)}, or a scene sequence {SCENE_FORM})")
    return named


def bench_data(preset: str, cfg: BenchConfig, frames: int, quiet: bool = False, depth_model: str = "exact",
               scene: str = "room", exact: bool = False) -> pathlib.Path:
    """The generated sequence of a preset (``runs/bench_<preset>[_<scene>]_<w>x<h>_seed<s>[_sensor]``)
    or of a named scene sequence (:func:`scene_settings`; ``runs/bench_<name>_<w>x<h>_seed<s>``),
    made again when missing, shorter than ``frames`` (``exact``: of another length, for benchmarks that
    run the whole folder) or older than the depth noise record in camera.yaml."""
    from ..synthetic import generate_sequence

    settings = _synth_settings(preset, scene)
    suffix = "" if depth_model == "exact" else f"_{depth_model}"
    label = preset if scene == "room" else f"{preset}_{scene}"
    data = pathlib.Path("runs") / f"bench_{label}_{cfg.width}x{cfg.height}_seed{cfg.seed}{suffix}"
    seq = open_sequence(data) if (data / "exposure.txt").is_file() else None
    if seq is None or len(seq) < frames or (exact and len(seq) != frames) or "depth_sigma" not in seq.meta:
        synth = SynthConfig(**{**settings, "frames": frames, "width": cfg.width, "height": cfg.height, "seed": cfg.seed,
                               "depth_model": depth_model})
        generate_sequence(synth, data, progress=not quiet)
    return data


def with_hidden_exposure(seqs: dict, names: str) -> dict:
    """``seqs`` plus, for each of ``names`` (or 'all'), ``<name>_noexp``: the same images with the
    exposure metadata removed (``synthetic.exposure_hidden_copy``, next to the data)."""
    from ..synthetic import exposure_hidden_copy

    chosen = list(seqs) if names.strip() == "all" else [n for n in names.split(",") if n]
    unknown = [n for n in chosen if n not in seqs]
    if unknown:
        raise MbavoError(f"bench.hide_exposure: no sequence named {', '.join(unknown)} (have {', '.join(seqs)})")
    out = {}
    for name, path in seqs.items():
        out[name] = path
        if name in chosen:
            path = pathlib.Path(path)
            out[f"{name}_noexp"] = exposure_hidden_copy(path, path.parent / f"{path.name}_noexp")
    return out


def real_clip(value: str) -> pathlib.Path:
    """The real clip a ``--tum`` / ``--kitti`` value names: the path as given when it exists, else the
    folder of that name in the shared data folder (``synthetic.scene.default_shared_data``), so that
    the defaults (``../shared/data/...``) work from any working folder."""
    from ..synthetic.scene import default_shared_data

    path = pathlib.Path(value).expanduser()
    shared = default_shared_data()
    if path.exists() or shared is None or not (shared / path.name).is_dir():
        return path  # missing: the loader says so in one line
    return shared / path.name


def tum_blurred(cfg: BenchConfig, quiet: bool = False, blur_px: float = 20.0) -> pathlib.Path:
    """``runs/bench_tum_blurred<px>``: the TUM clip ``cfg.tum`` blurred by ``mbavo synth --from`` by
    ``blur_px`` (mean over frames), made once."""
    from ..synthetic import blur_real_sequence

    out = pathlib.Path("runs") / f"bench_tum_blurred{blur_px:g}"
    if not (out / "exposure.txt").is_file():
        blur_real_sequence(open_sequence(real_clip(cfg.tum)), out, blur_px=blur_px, progress=not quiet)
    return out


@dataclasses.dataclass(frozen=True)
class Generated:
    """One generated sequence of a benchmark (``bench_data``'s arguments)."""

    preset: str
    seed: int
    width: int
    height: int
    depth_model: str = "exact"
    scene: str = "room"


def generated_sequences(cfg: BenchConfig) -> dict[str, Generated]:
    """The odometry benchmark's generated sequences by table name: ``cfg.presets``, then
    ``cfg.sensor_presets`` (``<preset>_sensor``), then ``cfg.scenes`` x ``cfg.scene_presets``
    (``<preset>_<scene>``), each at every size (``cfg.size_list``) and seed (``cfg.seed_list``).
    With one size and one seed a name is just that; with more, each name ends ``_<w>x<h>_s<seed>``."""
    split = lambda text: [x for x in text.split(",") if x]
    kinds = [(p, "exact", "room", p) for p in split(cfg.presets)]
    kinds += [(p, "sensor", "room", f"{p}_sensor") for p in split(cfg.sensor_presets)]
    kinds += [(p, "exact", s, f"{p}_{s}") for s in split(cfg.scenes) for p in split(cfg.scene_presets)]
    sizes, seeds = cfg.size_list(), cfg.seed_list()
    tagged = len(sizes) > 1 or len(seeds) > 1
    return {label + (f"_{w}x{h}_s{s}" if tagged else ""): Generated(p, s, w, h, depth_model, scene)
            for p, depth_model, scene, label in kinds for w, h in sizes for s in seeds}


def make_generated(g: Generated, cfg: BenchConfig, quiet: bool = False) -> pathlib.Path:
    """The folder of ``g`` (:func:`bench_data`, exactly ``cfg.frames`` long)."""
    at = dataclasses.replace(cfg, seed=g.seed, width=g.width, height=g.height)
    return bench_data(g.preset, at, cfg.frames, quiet, depth_model=g.depth_model, scene=g.scene, exact=True)
