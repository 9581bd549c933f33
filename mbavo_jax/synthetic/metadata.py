"""Sequences without exposure metadata, as TUM, EuRoC and KITTI data come.

``hide_exposure_info`` strips the exposure time from a written sequence folder (camera.yaml's
``exposure_ms``, times.txt) and keeps the ground-truth exposure paths only for evaluation, as
``groundtruth_exposure.txt`` (``open_tum`` still reads them into ``Sequence.exposure_paths``).
camera.yaml's ``readout_ms`` (a rolling shutter's readout time, a property of the sensor, not of the
exposure) and the per-row ground truth ``exposure_rows.txt`` are kept.
``exposure_hidden_copy`` does the same to a cheap copy, so one set of images can be run with and
without the metadata.
"""

from __future__ import annotations

import pathlib
import shutil

import yaml

from ..errors import MbavoError
from ..io import read_text

__all__ = ["hide_exposure_info", "exposure_hidden_copy", "GROUNDTRUTH_EXPOSURE", "EXPOSURE_ROWS"]

GROUNDTRUTH_EXPOSURE = "groundtruth_exposure.txt"
EXPOSURE_ROWS = "exposure_rows.txt"  # per-row exposure paths of a rolling-shutter sequence: ground truth, kept as is


def _drop_yaml_key(path: pathlib.Path, key: str, record: dict | None = None) -> None:
    """Remove ``key`` from the YAML mapping at ``path`` (other keys kept in order), then set ``record``."""
    if not path.is_file():
        return
    data = yaml.safe_load(read_text(path, path.name)) or {}
    data.pop(key, None)
    data.update(record or {})
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def hide_exposure_info(folder) -> None:
    """Turn the sequence ``folder`` into one without exposure metadata: camera.yaml loses
    ``exposure_ms``, times.txt goes, exposure.txt becomes groundtruth_exposure.txt and synth.yaml
    (when there is one) records ``exposure_info: false``. Running it twice changes nothing more."""
    folder = pathlib.Path(folder)
    _drop_yaml_key(folder / "camera.yaml", "exposure_ms")
    (folder / "times.txt").unlink(missing_ok=True)
    if (folder / "exposure.txt").is_file():
        (folder / "exposure.txt").replace(folder / GROUNDTRUTH_EXPOSURE)
    _drop_yaml_key(folder / "synth.yaml", "exposure_info", {"exposure_info": False})


def exposure_hidden_copy(src, dst) -> pathlib.Path:
    """Make ``dst`` a copy of the sequence folder ``src`` without exposure metadata: its sub-folders
    (rgb/, depth/, sharp/) are symlinks to ``src``'s, its files are copied, then
    :func:`hide_exposure_info`. A file or symlink already in ``dst`` under one of those names is
    replaced; returns ``dst``."""
    src, dst = pathlib.Path(src).resolve(), pathlib.Path(dst)
    if not src.is_dir():
        raise MbavoError(f"{src}: sequence folder not found")
    dst.mkdir(parents=True, exist_ok=True)
    if dst.resolve() == src:
        raise MbavoError(f"{dst}: the copy must not be the source folder")
    for item in sorted(src.iterdir()):
        target = dst / item.name
        if target.is_symlink() or target.is_file():
            target.unlink()
        elif target.exists():
            raise MbavoError(f"{target}: exists and is a folder; choose a new destination")
        if item.is_dir():
            target.symlink_to(item, target_is_directory=True)
        else:
            shutil.copy2(item, target)
    hide_exposure_info(dst)
    return dst
