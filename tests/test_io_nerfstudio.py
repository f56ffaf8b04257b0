"""nerfstudio `transforms.json` captures (what Polycam, Record3D, KIRI Engine and ns-process-data
export): conversion to our conventions, undistortion, and refusal of unsafe or inconsistent files."""
from __future__ import annotations

import io
import json
import stat
import zipfile

import cv2
import numpy as np
import pytest
import torch

from capture_fixtures import PANORAMA, write_nerfstudio, zip_dir
from core.camera import Camera, Intrinsics
from core.io.archive import ArchiveError, ZipFiles, member_name
from core.io.nerfstudio import Z_UP_TO_Y_UP, inspect_nerfstudio, load_nerfstudio
from core.sim.panorama_room import PanoramaRoom, load_panorama, render_clip
from core.sim.state import pose_from_yaw_pitch
from core.tracking.room import assumed_room

W, H = 96, 72


@pytest.fixture(scope="module")
def scene():
    intr = Intrinsics(80.0, 80.0, 47.5, 36.5, W, H)  # off-centre principal point on purpose
    poses = [pose_from_yaw_pitch((0.3 * i, 0.1, -0.2 * i), 10 * i, 5.0) for i in range(4)]
    room = PanoramaRoom(load_panorama(PANORAMA, 128), assumed_room(), torch.zeros(3))
    ldr, depth, _ = render_clip(room, [Camera(intr, p) for p in poses], supersample=1)
    return ldr.numpy(), depth.numpy(), intr, np.stack([p.numpy() for p in poses])


def write_capture(root, ldr, depth, intr, poses, **kw):
    return write_nerfstudio(root, ldr, depth, intr, poses, **kw)


def test_directory_capture_keeps_opengl_poses_intrinsics_and_depth(tmp_path, scene):
    ldr, depth, intr, poses = scene
    cap = load_nerfstudio(write_capture(tmp_path / "cap", ldr, depth, intr, poses))
    assert cap.frames.shape == (4, H, W, 3)
    assert np.abs(cap.frames - ldr).max() <= 0.5 / 255 + 1e-6
    assert np.allclose(cap.poses, poses, atol=1e-12)  # OpenGL camera = ours: no conversion
    assert cap.intrinsics == {"fx": 80.0, "fy": 80.0, "cx": 47.5, "cy": 36.5, "width": W, "height": H}
    assert np.nanmax(np.abs(cap.depth - depth)) < 0.6e-3  # millimetre PNG quantisation
    assert cap.metadata["camera_model"] == "PINHOLE" and cap.metadata["world_rotation_applied"] is None


def test_zip_with_a_wrapping_folder_loads_like_the_directory(tmp_path, scene):
    ldr, depth, intr, poses = scene
    root = write_capture(tmp_path / "cap", ldr, depth, intr, poses)
    a, b = load_nerfstudio(root), load_nerfstudio(zip_dir(root, "my scan/"))
    assert np.array_equal(a.frames, b.frames) and np.array_equal(a.poses, b.poses)
    assert np.array_equal(np.nan_to_num(a.depth), np.nan_to_num(b.depth))
    info = inspect_nerfstudio(zip_dir(root, "my scan/"))
    assert info["frames"] == 4 and info["depth"] == "per frame"


def test_z_up_world_is_turned_to_y_up(tmp_path, scene):
    ldr, depth, intr, poses = scene
    z_up = np.linalg.inv(Z_UP_TO_Y_UP)  # how a COLMAP-based export stores our y-up poses
    cap = load_nerfstudio(write_capture(tmp_path / "cap", ldr, depth, intr, poses, world=z_up, with_depth=False))
    assert np.allclose(cap.poses, poses, atol=1e-9)
    assert cap.metadata["world_rotation_applied"] is not None
    assert any("+z up" in n for n in cap.metadata["notes"])


def test_opencv_distortion_is_removed(tmp_path, scene):
    _, depth, intr, poses = scene
    v, u = np.mgrid[0:H, 0:W] + 0.5
    pattern = 0.5 + 0.4 * np.sin(u / 2.0) * np.cos(v / 2.5)  # fine texture: misplaced pixels show
    ldr = np.repeat(pattern[None, ..., None], 4, 0).repeat(3, -1).astype(np.float32)
    k1, k2, p1, p2 = -0.25, 0.06, 0.001, -0.002
    K = np.array([[intr.fx, 0, intr.cx - 0.5], [0, intr.fy, intr.cy - 0.5], [0, 0, 1]])
    # distort: each distorted pixel looks up where its undistorted ray lands in the pinhole image
    grid = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 1, 2).astype(np.float64)
    und = cv2.undistortPoints(grid, K, np.array([k1, k2, p1, p2]), P=K).reshape(H, W, 2).astype(np.float32)
    distorted = np.stack([cv2.remap(f, und[..., 0], und[..., 1], cv2.INTER_LINEAR) for f in ldr])
    root = write_capture(tmp_path / "cap", distorted, depth, intr, poses, with_depth=False,
                         extra={"camera_model": "OPENCV", "k1": k1, "k2": k2, "p1": p1, "p2": p2})
    cap = load_nerfstudio(root)
    inner = (slice(12, H - 12), slice(16, W - 16))
    err_after = np.abs(cap.frames[:, inner[0], inner[1]] - ldr[:, inner[0], inner[1]]).mean()
    err_before = np.abs(distorted[:, inner[0], inner[1]] - ldr[:, inner[0], inner[1]]).mean()
    assert err_after < 0.2 * err_before, (err_after, err_before)
    assert any("distortion" in n for n in cap.metadata["notes"])


def test_downscaled_images_rescale_the_intrinsics(tmp_path, scene):
    ldr, depth, intr, poses = scene
    small = np.stack([cv2.resize(f, (W // 2, H // 2), interpolation=cv2.INTER_AREA) for f in ldr])
    cap = load_nerfstudio(write_capture(tmp_path / "cap", small, depth, intr, poses, with_depth=False))
    assert cap.intrinsics["fx"] == pytest.approx(40.0) and cap.intrinsics["cx"] == pytest.approx(47.5 / 2)


def test_partial_depth_is_ignored_with_a_warning(tmp_path, scene):
    ldr, depth, intr, poses = scene
    root = write_capture(tmp_path / "cap", ldr, depth, intr, poses)
    meta = json.loads((root / "transforms.json").read_text())
    del meta["frames"][2]["depth_file_path"]
    (root / "transforms.json").write_text(json.dumps(meta))
    cap = load_nerfstudio(root)
    assert cap.depth is None and any("depth ignored" in w for w in cap.warnings)


def _broken(tmp_path, scene, edit):
    ldr, depth, intr, poses = scene
    root = write_capture(tmp_path / "cap", ldr, depth, intr, poses, with_depth=False)
    meta = json.loads((root / "transforms.json").read_text())
    edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ArchiveError) as exc:
        load_nerfstudio(root)
    return exc.value


@pytest.mark.parametrize(
    "edit, field, code",
    [
        (lambda m: m.update(frames=[]), "frames", "shape_mismatch"),
        (lambda m: m.update(camera_model="EQUIRECTANGULAR"), "camera_model", "unsupported_codec"),
        (lambda m: m.pop("fl_x"), "fl_x", "shape_mismatch"),
        (lambda m: m.update(fl_x=-3), "fl_x", "shape_mismatch"),
        (lambda m: m["frames"][1].update(file_path="images/missing.png"), "frames[1].file_path", "not_found"),
        (lambda m: m["frames"][1].update(file_path="../../etc/passwd"), "frames[1].file_path", "not_found"),
        (lambda m: m["frames"][1].update(file_path="/etc/passwd"), "frames[1].file_path", "not_found"),
        (lambda m: m["frames"][2].pop("transform_matrix"), "frames[2].transform_matrix", "shape_mismatch"),
        (
            lambda m: m["frames"][2].update(transform_matrix=[[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]),
            "frames[2].transform_matrix",
            "shape_mismatch",
        ),
        (
            lambda m: m["frames"][2].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]),
            "frames[2].transform_matrix",
            "shape_mismatch",
        ),
        (lambda m: m["frames"][3].update(fl_x=200.0), "frames[3].fl_x", "shape_mismatch"),
    ],
)
def test_bad_transforms_json_names_the_field(tmp_path, scene, edit, field, code):
    err = _broken(tmp_path, scene, edit)
    assert err.field == f"transforms.json: {field}", (err.field, str(err))
    assert err.code == code and field in str(err)


def test_unreadable_index_and_missing_index(tmp_path):
    (tmp_path / "a").mkdir()
    with pytest.raises(ArchiveError, match="no transforms.json") as exc:
        load_nerfstudio(tmp_path / "a")
    assert exc.value.code == "not_found"
    (tmp_path / "a" / "transforms.json").write_text("{not json")
    with pytest.raises(ArchiveError, match="not valid UTF-8 JSON"):
        load_nerfstudio(tmp_path / "a")


def test_symlink_out_of_a_directory_capture_is_refused(tmp_path, scene):
    ldr, depth, intr, poses = scene
    root = write_capture(tmp_path / "cap", ldr, depth, intr, poses, with_depth=False)
    secret = tmp_path / "secret.png"
    secret.write_bytes((root / "images/frame_00001.png").read_bytes())
    (root / "images/frame_00001.png").unlink()
    (root / "images/frame_00001.png").symlink_to(secret)
    with pytest.raises(ArchiveError, match="not in the capture"):
        load_nerfstudio(root)


def _zip(entries) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for info, data in entries:
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, data)
    return buf.getvalue()


def test_unsafe_zips_are_refused():
    link = zipfile.ZipInfo("images/a.png")
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    with pytest.raises(ArchiveError, match="symbolic link"):
        ZipFiles(_zip([(link, "/etc/passwd")]))
    with pytest.raises(ArchiveError, match="leaves the capture"):
        ZipFiles(_zip([(zipfile.ZipInfo("../evil.png"), b"x")]))
    with pytest.raises(ArchiveError, match="absolute"):
        ZipFiles(_zip([(zipfile.ZipInfo("/abs.png"), b"x")]))
    with pytest.raises(ArchiveError, match="zip bomb") as exc:
        ZipFiles(_zip([(zipfile.ZipInfo("images/zeros.png"), b"\0" * (8 << 20))]))
    assert exc.value.code == "too_large"
    with pytest.raises(ArchiveError, match="entries"):
        ZipFiles(_zip([(zipfile.ZipInfo(f"f{i}"), b"x") for i in range(30)]), max_members=20)
    with pytest.raises(ArchiveError, match="not a readable zip"):
        ZipFiles(b"PK\x03\x04 definitely not a zip")


def test_member_names_are_normalised_or_refused():
    assert member_name("./images//a.png") == "images/a.png"
    for bad in ("", "a\\b.png", "C:/x.png", "a/../../b", "a\x00b"):
        with pytest.raises(ArchiveError):
            member_name(bad)
