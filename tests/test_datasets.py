"""Loaders (TUM, KITTI, EuRoC, DSO, image folder) on real and hand-made sequences, and bad input:
each bad file gives a one-line error naming the file, exit status 1, never a traceback (``mbavo``
runs in-process: the ``mbavo`` fixture of conftest.py)."""

from __future__ import annotations

import json
import pathlib

import cv2
import numpy as np
import pytest

from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import DataError

from .conftest import H, W, depth_of, make_tum, shared_dataset, write_depth


def test_tum_real_clip():
    seq = open_sequence(shared_dataset("tum_fr1_xyz_head37"))
    assert seq.kind == "tum" and len(seq) == 37 and seq.has_depth
    assert (seq.camera.width, seq.camera.height) == (640, 480) and seq.camera_model["model"] == "radtan"
    assert seq.camera_model["intrinsics"][0] == pytest.approx(517.3) and float(seq.camera.fx) > 517.3  # undistorted once at load
    f = seq[10]
    assert f.image.shape == (480, 640) and f.image.dtype == np.float32 and 0 <= f.image.min() and f.image.max() <= 1
    assert f.depth.shape == (480, 640) and np.nanmedian(f.depth) > 0.3 and np.isnan(f.depth).any()
    assert seq.groundtruth[1].shape == (3000, 7)


def test_kitti_real_clip():
    seq = open_sequence(shared_dataset("kitti07_head160"))
    assert seq.kind == "kitti" and len(seq) == 160 and not seq.has_depth
    assert float(seq.camera.fx) == pytest.approx(707.0912) and float(seq.camera.cy) == pytest.approx(183.1104)
    assert seq[159].image.shape == (370, 1226)
    assert seq.groundtruth[1].shape == (160, 7)


def test_loading_is_lazy(tmp_path, monkeypatch):
    root = make_tum(tmp_path / "seq", n=5)
    import mbavo_jax.datasets.loaders as loaders

    calls = []
    real = loaders.read_image_gray
    monkeypatch.setattr(loaders, "read_image_gray", lambda p: calls.append(p) or real(p))
    seq = open_sequence(root)
    assert calls == [] and len(seq) == 5
    seq[3]
    assert len(calls) == 1


def test_tum_association_and_exposure(tmp_path):
    """Each rgb frame gets the depth image nearest in time (within 20 ms), whatever the order and
    count of depth.txt's entries; exposure times come from times.txt, else camera.yaml's exposure_ms."""
    root = make_tum(tmp_path / "seq", n=6)
    rgb_stamps = 10.0 + np.arange(6) / 30
    # Depth stamps jittered by up to 9 ms around their rgb frame, plus decoys holding other depths: one
    # before the first frame (a pairing by position would be off by one), one 11 ms after frame 1
    # whose true partner is 7 ms before it, one 12 ms before frame 4 whose partner is 6 ms after it,
    # and one 13 ms after frame 2 (its partner: 9 ms after). Every decoy is within the 20 ms window.
    jitter = [0.002, -0.007, 0.009, -0.004, 0.006, -0.001]
    entries = [(rgb_stamps[k] + jitter[k], f"depth/true{k}.png", depth_of(k)) for k in range(6)]
    decoys = [(rgb_stamps[0] - 0.030, 9.0), (rgb_stamps[1] + 0.011, 9.25), (rgb_stamps[4] - 0.012, 9.5), (rgb_stamps[2] + 0.013, 9.75)]
    entries += [(t, f"depth/decoy{i}.png", d) for i, (t, d) in enumerate(decoys)]
    entries.sort()
    for _, name, metres in entries:
        write_depth(root / name, metres)
    (root / "depth.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} {name}\n" for t, name, _ in entries))

    seq = open_sequence(root)
    assert seq.has_depth and len(seq) == 6
    assert seq.exposures is None and seq[0].exposure is None  # neither times.txt nor exposure_ms
    for k in range(6):
        f = seq[k]
        assert f.timestamp == pytest.approx(rgb_stamps[k]) and pathlib.Path(f.path).name == f"{rgb_stamps[k]:.6f}.png"
        assert f.depth.shape == (H, W)
        np.testing.assert_allclose(f.depth, depth_of(k), rtol=0, atol=1e-6, err_msg=f"frame {k} got the wrong depth image")

    # an rgb frame with no depth within 20 ms is an error naming depth.txt when it is loaded
    last = rgb_stamps[-1] + 0.1
    cv2.imwrite(str(root / "rgb" / "late.png"), np.zeros((H, W), np.uint8))
    with open(root / "rgb.txt", "a") as fh:
        fh.write(f"{last:.6f} rgb/late.png\n")
    seq = open_sequence(root)
    np.testing.assert_allclose(seq[5].depth, depth_of(5), atol=1e-6)
    with pytest.raises(DataError, match="depth.txt"):
        seq[6]
    (root / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_stamps))

    # a constant exposure time from camera.yaml (milliseconds)
    cam = (root / "camera.yaml").read_text()
    (root / "camera.yaml").write_text(cam + "exposure_ms: 12.5\n")
    seq = open_sequence(root)
    np.testing.assert_allclose(seq.exposures, np.full(6, 0.0125))
    assert [seq[k].exposure for k in range(6)] == pytest.approx([0.0125] * 6)
    # per-frame exposure times from times.txt (DSO style: id timestamp exposure_ms) win over camera.yaml's
    exposure_ms = [8.0, 9.5, 11.0, 12.5, 14.0, 15.5]
    (root / "times.txt").write_text("".join(f"{k} {t:.6f} {e}\n" for k, (t, e) in enumerate(zip(rgb_stamps, exposure_ms))))
    seq = open_sequence(root)
    np.testing.assert_allclose(seq.exposures, np.array(exposure_ms) / 1000)
    assert [seq[k].exposure for k in range(6)] == pytest.approx([e / 1000 for e in exposure_ms])
    np.testing.assert_allclose(seq[3].depth, depth_of(3), atol=1e-6)  # still paired by time


def test_dso_folder(tmp_path):
    root = tmp_path / "dso"
    (root / "images").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(root / "images" / f"{i:05d}.png"), np.full((H, W), 100 + i, np.uint8))
    (root / "times.txt").write_text("".join(f"{i:05d} {1.0 + i * 0.05:.6f} {12.5:.3f}\n" for i in range(3)))
    (root / "camera.txt").write_text(f"Pinhole 0.5 0.6 0.5 0.5 0\n{W} {H}\ncrop\n{W} {H}\n")
    seq = open_sequence(root)
    assert seq.kind == "dso" and len(seq) == 3
    assert float(seq.camera.fx) == pytest.approx(0.5 * W) and float(seq.camera.cx) == pytest.approx(0.5 * W - 0.5)
    assert seq[1].exposure == pytest.approx(0.0125)


def test_euroc_folder(tmp_path):
    cam = tmp_path / "euroc" / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for i in range(3):
        name = f"{1403636579763555584 + i * 50000000}.png"
        cv2.imwrite(str(cam / "data" / name), np.full((H, W), 50, np.uint8))
        lines.append(f"{name[:-4]},{name}")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0.1, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"
        f"resolution: [{W}, {H}]\nintrinsics: [30.0, 31.0, 15.5, 11.5]\n"
    )
    gt = tmp_path / "euroc" / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    (gt / "data.csv").write_text("#t,px,py,pz,qw,qx,qy,qz\n1403636579763555584,1,2,3,1,0,0,0\n1403636579813555584,1,2,3.1,1,0,0,0\n")
    seq = open_sequence(tmp_path / "euroc")
    assert seq.kind == "euroc" and len(seq) == 3 and float(seq.camera.fy) == 31.0
    assert seq.timestamps[1] - seq.timestamps[0] == pytest.approx(0.05)
    np.testing.assert_allclose(seq.groundtruth[1][0], [1.1, 2, 3, 0, 0, 0, 1], atol=1e-6)  # body pose ∘ T_BS


def test_image_folder(tmp_path):
    root = tmp_path / "imgs"
    root.mkdir()
    for i in range(2):
        cv2.imwrite(str(root / f"{i}.png"), np.zeros((H, W), np.uint8))
    (root / "camera.yaml").write_text(f"fx: 30\nfy: 30\ncx: 15\ncy: 11\nwidth: {W}\nheight: {H}\nfps: 10\n")
    seq = open_sequence(root)
    assert seq.kind == "folder" and list(seq.timestamps) == [0.0, 0.1]


# ------------------------------------------------------------------------------------ bad input


def _corrupt(root: pathlib.Path, what: str):
    if what == "missing_image":
        next((root / "rgb").glob("*.png")).unlink()
        return "rgb/"
    if what == "tum_columns":
        with open(root / "groundtruth.txt", "a") as f:
            f.write("10.5 0 0 0 0 0 1\n")
        return "groundtruth.txt:5"
    if what == "unsorted":
        lines = (root / "rgb.txt").read_text().splitlines()
        lines[1], lines[2] = lines[2], lines[1]
        (root / "rgb.txt").write_text("\n".join(lines) + "\n")
        return "rgb.txt:3"
    if what == "duplicate":
        lines = (root / "groundtruth.txt").read_text().splitlines()
        lines.insert(1, lines[0])
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
        return "groundtruth.txt:2"
    if what == "depth_size":
        p = next((root / "depth").glob("*.png"))
        cv2.imwrite(str(p), np.full((H // 2, W // 2), 5000, np.uint16))
        return p.name
    if what == "depth_dtype":
        p = next((root / "depth").glob("*.png"))
        cv2.imwrite(str(p), np.full((H, W), 50, np.uint8))
        return p.name
    if what == "corrupt_png":
        p = sorted((root / "rgb").glob("*.png"))[1]
        p.write_bytes(b"\x89PNG\r\n\x1a\nthis is not a png")
        return p.name
    if what == "camera_negative":
        (root / "camera.yaml").write_text(f"fx: -30\nfy: 30\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\n")
        return "camera.yaml"
    if what == "camera_missing_key":
        (root / "camera.yaml").write_text(f"fx: 30\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\n")
        return "camera.yaml"
    if what == "camera_depth_sigma":
        (root / "camera.yaml").write_text(f"fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\ndepth_sigma: [0.001]\n")
        return "camera.yaml"
    if what == "quaternion":
        with open(root / "groundtruth.txt", "a") as f:
            f.write("10.5 0 0 0 0 0 0 2\n")
        return "groundtruth.txt:5"
    raise ValueError(what)


@pytest.mark.parametrize(
    "what",
    ["missing_image", "tum_columns", "unsorted", "duplicate", "depth_size", "depth_dtype", "corrupt_png",
     "camera_negative", "camera_missing_key", "camera_depth_sigma", "quaternion"],
)
def test_bad_input_is_one_line_error(tmp_path, what, mbavo):
    root = make_tum(tmp_path / "seq")
    where = _corrupt(root, what)
    r = mbavo("info", root, "--check")
    assert r.returncode == 1, r
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mbavo: error: ") and where in lines[0], r.stderr


def test_missing_sequence_and_no_overlap(tmp_path, mbavo):
    r = mbavo("info", tmp_path / "nope")
    assert r.returncode == 1 and "not found" in r.stderr and "Traceback" not in r.stderr
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("".join(f"{t} 0 0 {t} 0 0 0 1\n" for t in range(5)))
    b.write_text("".join(f"{t + 100} 0 0 {t} 0 0 0 1\n" for t in range(5)))
    r = mbavo("eval", "ape", a, b)
    assert r.returncode == 1 and "no overlapping timestamps" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = mbavo("eval", "ape", a, tmp_path / "missing.txt")
    assert r.returncode == 1 and "missing.txt" in r.stderr and "not found" in r.stderr


def test_image_size_change_mid_sequence(tmp_path, mbavo):
    root = make_tum(tmp_path / "seq", depth=False)
    p = sorted((root / "rgb").glob("*.png"))[2]
    cv2.imwrite(str(p), np.zeros((H + 2, W), np.uint8))
    with pytest.raises(DataError, match="image size"):
        open_sequence(root)[2]
    info = json.loads(mbavo("info", root, "--format", "json").stdout)
    assert info["frames"] == 4
