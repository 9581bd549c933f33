"""DSO as a peer of ``mbavo bench mono`` (``mbavo_jax.bench.dso``): DSO's dataset layout written from
any sequence, its result.txt read strictly, a run through a stand-in ``dso_dataset`` (a shell script
that answers as DSO does: these tests check our adapter, not DSO), and the bench's new columns on
run folders made by hand."""

from __future__ import annotations

import pathlib
import stat

import numpy as np
import pytest

from mbavo_jax.bench import dso as bd
from mbavo_jax.bench import mono as bm
from mbavo_jax.config import EvalConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.datasets.base import Frame, Sequence
from mbavo_jax.datasets.loaders import open_dso
from mbavo_jax.errors import DataError, MbavoError
from mbavo_jax.geometry import PinholeCamera
from mbavo_jax.io import read_tum_trajectory, write_tum_trajectory
from tests.conftest import make_tum

STAMPS = 10.0 + np.arange(10) / 30


def tiny_sequence(width: int, height: int, n: int = 3, groundtruth=None) -> Sequence:
    """n frames of seeded noise at ``width`` x ``height``, stamped like STAMPS."""
    cam = PinholeCamera.create(0.9 * width, 0.9 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    images = np.random.default_rng(0).random((n, height, width)).astype(np.float32)
    load = lambda i: Frame(i, float(STAMPS[i]), images[i], cam)
    return Sequence("tiny", pathlib.Path("."), cam, STAMPS[:n].copy(), load, groundtruth=groundtruth)


def test_dso_camera_sizes_follow_its_pyramid():
    """Multiples of 16 pass as they are ("none"); other sizes are resampled ("crop") to multiples of
    16 at about the same aspect: KITTI's 1241x376 to 1216x368, as DSO's KITTI files do."""
    assert bd.dso_output_size(1241, 376) == ("crop", 1216, 368)
    assert bd.dso_output_size(320, 240) == ("none", 320, 240)
    assert bd.dso_output_size(640, 480) == ("none", 640, 480)
    assert bd.dso_output_size(32, 24) == ("crop", 16, 16)


def test_the_dso_folder_reads_back_as_the_sequence(tmp_path):
    """images/ (8-bit, in frame order), times.txt ("id timestamp", no exposure: DSO then uses 1 for
    every frame) and camera.txt; our DSO loader reads it back as the same camera, stamps and images."""
    seq = tiny_sequence(64, 48)
    images = bd.write_dso_folder(seq, tmp_path / "dso")
    assert sorted(p.name for p in images.iterdir()) == ["000000.png", "000001.png", "000002.png"]
    assert (tmp_path / "dso" / "times.txt").read_text().splitlines() == [f"{i} {float(t)!r}" for i, t in enumerate(STAMPS[:3])]
    assert (tmp_path / "dso" / "camera.txt").read_text().splitlines() == ["Pinhole 57.6 57.6 31.5 23.5 0", "64 48", "none", "64 48"]
    back = open_dso(tmp_path / "dso")
    assert back.camera.as_dict() == seq.camera.as_dict() and back.exposures is None
    np.testing.assert_array_equal(back.timestamps, seq.timestamps)
    np.testing.assert_allclose(back[2].image, np.round(seq[2].image * 255) / 255, atol=1e-6)


def test_a_kitti_sized_camera_is_cropped(tmp_path):
    bd.write_dso_folder(tiny_sequence(1241, 376, n=1), tmp_path / "dso")
    assert (tmp_path / "dso" / "camera.txt").read_text().splitlines()[1:] == ["1241 376", "crop", "1216 368"]


def _result(path: pathlib.Path, lines: list[str]) -> pathlib.Path:
    path.write_text("".join(f"{s}\n" for s in lines))
    return path


def test_dso_results_are_read_strictly(tmp_path):
    """DSO's 15-digit stamps become the sequence's own; an empty file is no pose; a short line, a
    stamp of no frame or a non-unit quaternion is one DataError naming the file and line."""
    good = _result(tmp_path / "result.txt", [f"{STAMPS[k]:.15g} 0.1 0.2 {k} 0 0 0 1" for k in (2, 3, 5)])
    index, poses = bd.read_dso_result(good, STAMPS)
    assert index.tolist() == [2, 3, 5] and poses[:, 2].tolist() == [2.0, 3.0, 5.0]
    assert len(bd.read_dso_result(_result(tmp_path / "empty.txt", []), STAMPS)[0]) == 0
    cases = {"0.1 0.2 0.3 0 0 0 1": "expected 8 columns", f"{float(STAMPS[4]) + 0.012!r} 0 0 0 0 0 0 1": "is no frame of the sequence",
             f"{float(STAMPS[4])!r} 0 0 0 0 0 0 2": "quaternion norm", f"{float(STAMPS[4])!r} 0 0 nan 0 0 0 1": "non-finite"}
    for line, message in cases.items():
        bad = _result(tmp_path / "bad.txt", [f"{float(STAMPS[1])!r} 0 0 0 0 0 0 1", line])
        with pytest.raises(DataError, match=f"bad.txt:2: .*{message}"):
            bd.read_dso_result(bad, STAMPS)
    assert bd.dso_restarts("a\nRESETTING!\nb\nRESETTING!\n") == 2 and bd.dso_restarts("LOST!!\n") == 0


FAKE_DSO = """#!/bin/sh
# stands in for dso_dataset: checks its arguments and DSO's layout, restarts once, poses frames 1.. of times.txt
for a in "$@"; do case "$a" in files=*) files=${a#files=};; calib=*) calib=${a#calib=};; esac; done
[ -f "$calib" ] && [ -d "$files" ] && [ -f "$(dirname "$files")/times.txt" ] || { echo "bad layout"; exit 2; }
echo "$@" > args.txt
echo "RESETTING!"
%s
awk 'NR > 1 { printf "%%.15g 0 %%d %%d 0 0 0 1\\n", $2, NR %% 2, NR }' "$(dirname "$files")/times.txt" > result.txt
"""


def fake_dso(path: pathlib.Path, extra: str = "") -> pathlib.Path:
    path.write_text(FAKE_DSO % extra)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


def test_a_dso_run_through_a_stand_in_binary(tmp_path):
    """run_dso: DSO's arguments, the layout under run/input, result.txt as trajectory.txt on the
    sequence's stamps, the restart counted; a timeout, a crash and a missing binary are one line each."""
    seq = open_sequence(make_tum(tmp_path / "tum", n=5))
    facts = bd.run_dso(seq, tmp_path / "run", fake_dso(tmp_path / "dso_dataset"), timeout_s=60)
    assert facts["posed"] == 4 and facts["restarts"] == 1 and facts["frames"] == 5 and not facts["lost"]
    t, poses = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    np.testing.assert_allclose(t, seq.timestamps[1:], atol=1e-6)
    assert poses[:, 2].tolist() == [2.0, 3.0, 4.0, 5.0] and poses[:, 1].tolist() == [0.0, 1.0, 0.0, 1.0]
    assert (tmp_path / "run" / "args.txt").read_text().split()[2:] == list(bd.DSO_ARGS)
    assert (tmp_path / "run" / "input" / "camera.txt").read_text().splitlines()[2:] == ["crop", "16 16"]
    with pytest.raises(MbavoError, match="did not finish in 0.5 s"):
        bd.run_dso(seq, tmp_path / "slow", fake_dso(tmp_path / "slow_dso", "sleep 5"), timeout_s=0.5)
    with pytest.raises(MbavoError, match="exited with status 3 and wrote no result.txt \\(RESETTING!"):
        bd.run_dso(seq, tmp_path / "crash", fake_dso(tmp_path / "crash_dso", "exit 3"), timeout_s=60)
    with pytest.raises(MbavoError, match="not an executable file"):
        bd.run_dso(seq, tmp_path / "none", tmp_path / "missing", timeout_s=60)


def test_the_bench_runs_dso_when_given_its_binary(tmp_path):
    """run_mono_benchmark with only DSO: its row has the scores, posing and the seconds per frame;
    the method dso without a binary is refused."""
    seq_dir = make_tum(tmp_path / "tum", n=6)
    stamps = 10.0 + np.arange(6) / 30
    write_tum_trajectory(seq_dir / "groundtruth.txt", stamps, [[0, (k + 1) % 2, k + 1, 0, 0, 0, 1] for k in range(6)])  # as the stand-in poses
    results = bm.run_mono_benchmark({"tiny": seq_dir}, tmp_path / "out", methods=[bm.DSO_METHOD], progress=False,
                                    dso=str(fake_dso(tmp_path / "dso_dataset")))
    row = results["tiny"]["dso"]
    assert (row["first_posed"], row["posed"], row["restarts"]) == (1, 5, 1) and row["seconds_per_frame"] > 0
    assert row["ate_rmse_m"] < 1e-6 and "| tiny | dso | 0.0000 m (0.00 %) |" in bm.format_mono_table(results)
    with pytest.raises(MbavoError, match="method dso needs --dso PATH"):
        bm.run_mono_benchmark({"tiny": seq_dir}, tmp_path / "out", methods=["dso"], progress=False)


def _frames_csv(run: pathlib.Path, notes: list[str]) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "frames.csv").write_text("index,status,note\n" + "".join(f"{i},dropped,{n}\n" for i, n in enumerate(notes)))


def test_the_bench_columns_on_run_folders(tmp_path):
    """First posed frame, frames posed and restarts per run; ours and DSO's ATE over the frames both
    posed, each Sim(3)-aligned on that subset (ours is the truth scaled and moved: 0 there)."""
    rng = np.random.default_rng(1)
    gt = np.zeros((10, 7))
    gt[:, 0], gt[:, 1], gt[:, 6] = np.linspace(0, 1, 10), np.sin(np.arange(10)), 1.0
    seq = tiny_sequence(32, 32, n=10, groundtruth=(STAMPS.copy(), gt))
    ours, peer = tmp_path / "mono_n64", tmp_path / "dso"
    moved = gt.copy()
    moved[:, :3] = 2.0 * gt[:, :3] + [1.0, -2.0, 0.5]
    write_tum_trajectory(ours / "trajectory.txt", STAMPS[3:], moved[3:])
    _frames_csv(ours, ["", "lost after 3 drops: initialising again", "", "lost after 3 drops: initialising again"])
    noisy = gt.copy()
    noisy[:, :3] += rng.normal(scale=0.05, size=(10, 3))
    write_tum_trajectory(peer / "trajectory.txt", STAMPS[[0, 5, 6, 7, 8, 9]], noisy[[0, 5, 6, 7, 8, 9]])
    (peer / "dso.log").write_text("RESETTING!\n")
    assert bm.posing(seq.timestamps, ours, 0.01) == {"first_posed": 3, "posed": 7, "restarts": 2}
    assert bm.posing(seq.timestamps, peer, 0.01) == {"first_posed": 0, "posed": 6, "restarts": 1}
    assert bm.posing(seq.timestamps, tmp_path / "nothing", 0.01) == {"first_posed": None, "posed": 0, "restarts": 0}
    both = bm.ate_both_posed(seq, ours, peer, EvalConfig())
    assert both["both_posed"] == 5 and both["ate_both_m"] < 1e-6 and 0.01 < both["peer_ate_both_m"] < 0.1
    length = np.linalg.norm(np.diff(gt[5:, :3], axis=0), axis=1).sum()
    assert both["peer_ate_both_pct"] == pytest.approx(100 * both["peer_ate_both_m"] / length)
    row = {"mono_n64": {"frames": 10, "ate_rmse_m": 0.0}, "dso": {"frames": 10}}
    bm.compare_with_dso(seq, row, tmp_path)
    assert row["mono_n64"]["both_posed"] == 5 and "both_posed" not in row["dso"]
    row["mono_n64"].update(bm.posing(seq.timestamps, ours, 0.01), ate_pct=0.0, drift_trans_pct=1.0, drift_scale_pct=1.0, dropped=3,
                           initialising=0, keyframes=2, seconds_per_frame=1.0, track_s_per_frame=0.5, backend_s_per_frame=0.3,
                           other_s_per_frame=0.2, backend_s_per_keyframe=1.0, compile_s=0.0)
    row["dso"].update(bm.posing(seq.timestamps, peer, 0.01), seconds_per_frame=0.02)
    table = bm.format_mono_table({"seq": row})
    assert "| 3 / 7 of 10 / 2 | 0.00 % / " in table and "(5 frames) |" in table
    assert "| seq | dso | lost (4 dropped, ? initialising) |  |  |  | 0 / 6 of 10 / 1 |  |" in table
