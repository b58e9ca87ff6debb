"""KITTI / SemanticKITTI I/O: round trips, the pose maths, every bad-input error, atomicity, laziness."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from leap_core.datasets.kitti import (
    POSES_NOTE,
    Calib,
    KittiSequence,
    lidar_poses,
    read_calib,
    read_image,
    read_label,
    read_png16,
    read_poses,
    read_scan,
    read_scan_rows,
    scan_point_count,
    write_calib,
    write_image,
    write_label,
    write_png16,
    write_poses,
    write_scan,
)
from leap_core.errors import DatasetError, LeapError, PosesMissingError

# A real SemanticKITTI sequence 00 calib.txt (odometry format), plus the blank line and trailing spaces
# that hand-edited copies often have.
ODOMETRY_CALIB = """P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 \
0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 \
0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 \
0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 \
0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 \
0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 \
0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 \
0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 \
0.000000000000e+00 1.000000000000e+00 4.915215000000e-03

Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 \
-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 \
9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01   \n"""

P2_ROW = "7.2e+02 0 6.1e+02 45.4 0 7.2e+02 1.9e+02 -0.11 0 0 1 0.0038"
IDENTITY_ROW = "1 0 0 0 0 1 0 0 0 0 1 0"
AXIS_SWAP = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def assert_names(exc_info: pytest.ExceptionInfo[BaseException], path: Path) -> None:
    """The error is one line and names the file."""
    msg = str(exc_info.value)
    assert path.name in msg, msg
    assert "\n" not in msg


# ------------------------------------------------------------------------------------- round trips
def test_scan_round_trip(tmp_path: Path) -> None:
    pts = np.array([[1.5, -2.0, 0.25, 0.5], [100.0, 3.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], np.float32)
    path = tmp_path / "000000.bin"
    write_scan(path, pts)
    assert path.stat().st_size == 3 * 16
    out = read_scan(path)
    assert out.dtype == np.float32 and out.shape == (3, 4)
    np.testing.assert_array_equal(out, pts)


def test_scan_rows_are_the_rows_of_the_whole_scan(tmp_path: Path) -> None:
    pts = np.arange(40, dtype=np.float32).reshape(10, 4)
    pts[7, 2] = np.nan  # a row never asked for: not checked (the project stage read the whole scan)
    path = tmp_path / "000000.bin"
    path.write_bytes(pts.tobytes())
    rows = np.array([9, 0, 3, 3, 5])
    got = read_scan_rows(path, rows)
    assert got.dtype == np.float32 and got.shape == (5, 4)
    np.testing.assert_array_equal(got, pts[rows])
    assert read_scan_rows(path, np.zeros(0, np.int64)).shape == (0, 4)
    with pytest.raises(DatasetError, match=r"000000\.bin.*point 10 asked for, the scan holds 10"):
        read_scan_rows(path, [1, 10])
    with pytest.raises(DatasetError, match=r"point -1 asked for"):
        read_scan_rows(path, [-1])
    with pytest.raises(DatasetError, match=r"1 points have non-finite"):
        read_scan_rows(path, [6, 7])
    (tmp_path / "000001.bin").write_bytes(pts.tobytes()[:-4])
    with pytest.raises(DatasetError, match=r"000001\.bin.*not a multiple of 16"):
        read_scan_rows(tmp_path / "000001.bin", [0])


def test_empty_scan_round_trip(tmp_path: Path) -> None:
    write_scan(tmp_path / "e.bin", np.zeros((0, 4)))
    assert read_scan(tmp_path / "e.bin").shape == (0, 4)


def test_label_round_trip_keeps_instance_bits(tmp_path: Path) -> None:
    path = tmp_path / "000000.label"
    write_label(path, [10, 255, 40, 0], [0, 1, 0, 65535])
    raw = read_label(path, num_points=4)
    assert raw.dtype == np.uint32
    # 255 | 1 << 16 = 65791: a moving motorcyclist with instance 1.
    np.testing.assert_array_equal(raw, [10, 65791, 40, 65535 << 16])
    np.testing.assert_array_equal(raw & 0xFFFF, [10, 255, 40, 0])
    np.testing.assert_array_equal(raw >> 16, [0, 1, 0, 65535])


def test_label_without_instance_is_plain_semantic(tmp_path: Path) -> None:
    write_label(tmp_path / "a.label", np.array([72, 81], np.int64))
    np.testing.assert_array_equal(read_label(tmp_path / "a.label"), [72, 81])


def test_calib_round_trip(tmp_path: Path, tiny_calib: Calib) -> None:
    calib = tiny_calib
    write_calib(tmp_path / "calib.txt", calib)
    text = (tmp_path / "calib.txt").read_text()
    assert [ln.split(":")[0] for ln in text.splitlines()] == ["P2", "Tr"]
    back = read_calib(tmp_path / "calib.txt")
    np.testing.assert_allclose(back.P2, calib.P2, rtol=1e-12)
    np.testing.assert_allclose(back.Tr, calib.Tr, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(back.Tr[3], [0, 0, 0, 1])


def test_lidar_to_image_projects_a_point_ahead_to_the_principal_point(tiny_calib: Calib) -> None:
    calib = tiny_calib
    # The camera sits 8 cm below the LiDAR, so a point 10 m ahead at z = -0.08 is at camera height:
    # camera coords (0, 0, 10 - 0.27) after Tr.
    pt = np.array([10.0, 0.0, -0.08, 1.0])
    uvw = calib.lidar_to_image @ pt
    depth = 10.0 - 0.27
    assert uvw[2] == pytest.approx(depth)
    # u = cx + (fx * x - fx * 0.06) / z with x = 0; v = cy.
    assert uvw[0] / uvw[2] == pytest.approx(32.0 - 50.0 * 0.06 / depth)
    assert uvw[1] / uvw[2] == pytest.approx(24.0)


def test_reads_real_odometry_calib_with_blank_lines_and_trailing_spaces(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(ODOMETRY_CALIB)
    calib = read_calib(path)
    assert calib.P2[0, 3] == pytest.approx(45.38225)
    assert calib.P2[2, 3] == pytest.approx(3.779761e-03)
    assert calib.Tr[0, 1] == pytest.approx(-9.999672484946e-01)
    assert calib.Tr[2, 3] == pytest.approx(-2.921968648686e-01)
    # Real Tr is a rotation: Rᵀ R = I to the precision of the file.
    rot = calib.Tr[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-6)


def test_reads_crlf_and_bom(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_bytes(b"\xef\xbb\xbf" + ODOMETRY_CALIB.replace("\n", "\r\n").encode())
    assert read_calib(path).P2[0, 0] == pytest.approx(718.856)


def test_object_format_folds_r0_rect_into_tr(tmp_path: Path) -> None:
    """KITTI object files: P2 · R0_rect · Tr_velo_to_cam projects LiDAR points."""
    r0 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about z, easy to check
    velo = np.hstack([AXIS_SWAP, [[0.1], [0.2], [0.3]]])
    fmt = " ".join
    path = tmp_path / "000123.txt"
    path.write_text(
        f"P0: {P2_ROW}\nP1: {P2_ROW}\nP2: {P2_ROW}\nP3: {P2_ROW}\n"
        f"R0_rect: {fmt(str(v) for v in r0.ravel())}\n"
        f"Tr_velo_to_cam: {fmt(str(v) for v in velo.ravel())}\n"
        f"Tr_imu_to_velo: {fmt(['1'] * 12)}\n\n"
    )
    calib = read_calib(path)
    expected = np.eye(4)
    expected[:3, :3] = r0 @ AXIS_SWAP
    expected[:3, 3] = r0 @ [0.1, 0.2, 0.3]  # (-0.2, 0.1, 0.3)
    np.testing.assert_allclose(calib.Tr, expected, atol=1e-12)
    np.testing.assert_allclose(calib.Tr[:3, 3], [-0.2, 0.1, 0.3], atol=1e-12)


def test_tracking_format_without_colons(tmp_path: Path) -> None:
    velo = np.hstack([AXIS_SWAP, [[0.0], [0.0], [-0.5]]])
    path = tmp_path / "0001.txt"
    path.write_text(
        f"P2: {P2_ROW}\nR_rect 1 0 0 0 1 0 0 0 1\nTr_velo_cam {' '.join(str(v) for v in velo.ravel())}\n"
    )
    calib = read_calib(path)
    np.testing.assert_allclose(calib.Tr[:3], velo, atol=1e-12)


def test_odometry_tr_wins_over_velo_to_cam(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(ODOMETRY_CALIB + "Tr_velo_to_cam: " + " ".join(["1", "0", "0", "0"] * 3) + "\n")
    assert read_calib(path).Tr[0, 1] == pytest.approx(-9.999672484946e-01)


def test_poses_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, :4] = rng.normal(size=(4, 3, 4))
    write_poses(tmp_path / "poses.txt", poses)
    back = read_poses(tmp_path / "poses.txt")
    assert back.shape == (4, 4, 4)
    np.testing.assert_allclose(back, poses, rtol=1e-12)


def test_poses_skip_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 2 0 1 0 0 0 0 1 3\n\n")
    poses = read_poses(path)
    assert poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(poses[1, :3, 3], [2, 0, 3])


def test_lidar_pose_is_tr_inverse_pose_tr_by_hand(tiny_calib: Calib) -> None:
    """Tr = [R | t] with R the axis swap, t = (0, -0.08, -0.27); camera pose 1 = [Ry(90°) | (1, 0, 3)].

    LiDAR pose = [Rᵀ·Ry·R | Rᵀ·(Ry·t + T − t)]:
    Ry·R = [[1,0,0],[0,0,-1],[0,1,0]], Rᵀ·Ry·R = [[0,1,0],[-1,0,0],[0,0,1]] (−90° about LiDAR z);
    Ry·t + T − t = (−0.27 + 1, −0.08 + 0.08, 0 + 3 + 0.27) = (0.73, 0, 3.27), Rᵀ·(…) = (3.27, −0.73, 0).
    """
    tr = tiny_calib.Tr
    cam = np.tile(np.eye(4), (2, 1, 1))
    cam[1, :3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
    cam[1, :3, 3] = [1.0, 0.0, 3.0]
    out = lidar_poses(cam, tr)
    expected = np.array([[0.0, 1.0, 0.0, 3.27], [-1.0, 0.0, 0.0, -0.73], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1]])
    np.testing.assert_allclose(out[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(out[1], expected, atol=1e-12)
    # A pure forward camera motion of 2 m is a LiDAR motion of 2 m along x.
    cam[1] = np.eye(4)
    cam[1, 2, 3] = 2.0
    np.testing.assert_allclose(lidar_poses(cam, tr)[1][:3, 3], [2.0, 0.0, 0.0], atol=1e-12)


def test_lidar_poses_are_rebased_on_frame_zero(tiny_calib: Calib) -> None:
    """Moving the whole trajectory (any world frame G) leaves the re-based LiDAR poses unchanged."""
    tr = tiny_calib.Tr
    cam = np.tile(np.eye(4), (3, 1, 1))
    cam[1, :3, 3] = [0.5, 0.0, 2.0]
    cam[2, :3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
    g = np.eye(4)
    g[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    g[:3, 3] = [1000.0, -50.0, 7.0]
    np.testing.assert_allclose(lidar_poses(g[None] @ cam, tr), lidar_poses(cam, tr), atol=1e-9)


@pytest.mark.parametrize(("suffix", "hw"), [(".png", (37, 53)), (".jpg", (31, 45)), (".png", (1, 1))])
def test_image_round_trip_any_size(tmp_path: Path, suffix: str, hw: tuple[int, int]) -> None:
    h, w = hw
    yy, xx = np.mgrid[0:h, 0:w]
    # Smooth ramps so JPEG stays close; the three channels differ so an RGB/BGR swap would show.
    rgb = np.stack([xx * 255 // max(w - 1, 1), yy * 255 // max(h - 1, 1), np.full_like(xx, 40)], -1)
    rgb = rgb.astype(np.uint8)
    path = tmp_path / f"000000{suffix}"
    write_image(path, rgb)
    out = read_image(path)
    assert out.shape == (h, w, 3) and out.dtype == np.uint8
    if suffix == ".png":
        np.testing.assert_array_equal(out, rgb)
    else:
        assert np.abs(out.astype(int) - rgb).mean() < 6


def test_read_image_converts_grey_to_rgb(tmp_path: Path) -> None:
    path = tmp_path / "g.png"
    ok, buf = cv2.imencode(".png", np.full((4, 5), 77, np.uint8))
    assert ok
    path.write_bytes(buf.tobytes())
    out = read_image(path)
    assert out.shape == (4, 5, 3)
    assert (out == 77).all()


def test_png16_round_trip(tmp_path: Path) -> None:
    arr = np.array([[0, 1, 255, 256], [1000, 40000, 65534, 65535]], dtype=np.uint16)
    write_png16(tmp_path / "m.png", arr)
    out = read_png16(tmp_path / "m.png")
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, arr)


# ------------------------------------------------------------------------------ bad-input errors
def test_scan_size_not_multiple_of_16(tmp_path: Path) -> None:
    path = tmp_path / "000007.bin"
    path.write_bytes(b"\0" * 20)
    with pytest.raises(DatasetError, match="multiple of 16") as exc:
        read_scan(path)
    assert_names(exc, path)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_scan_non_finite(tmp_path: Path, bad: float) -> None:
    pts = np.zeros((3, 4), np.float32)
    pts[1, 2] = bad
    path = tmp_path / "000003.bin"
    path.write_bytes(pts.tobytes())
    with pytest.raises(DatasetError, match="1 points have non-finite") as exc:
        read_scan(path)
    assert_names(exc, path)


def test_missing_scan(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read scan") as exc:
        read_scan(tmp_path / "000404.bin")
    assert_names(exc, tmp_path / "000404.bin")


def test_label_count_differs_from_point_count(tmp_path: Path) -> None:
    path = tmp_path / "000002.label"
    write_label(path, [10, 40, 40])
    with pytest.raises(DatasetError, match="label count 3 != point count 4") as exc:
        read_label(path, num_points=4)
    assert_names(exc, path)


def test_label_size_not_multiple_of_4(tmp_path: Path) -> None:
    path = tmp_path / "000002.label"
    path.write_bytes(b"\1\0\0\0\1")
    with pytest.raises(DatasetError, match="multiple of 4") as exc:
        read_label(path)
    assert_names(exc, path)


def _calib_without(key: str) -> str:
    return "\n".join(ln for ln in ODOMETRY_CALIB.splitlines() if not ln.startswith(f"{key}:")) + "\n"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (_calib_without("P2"), "missing 'P2:'"),
        (_calib_without("Tr"), "missing 'Tr:'"),
        (ODOMETRY_CALIB.replace("P2: 7.188560000000e+02", "P2: nan"), "'P2' has non-finite"),
        (ODOMETRY_CALIB.replace("Tr: 4.276802385584e-04", "Tr: inf"), "'Tr' has non-finite"),
        (ODOMETRY_CALIB.replace("P2: 7.188560000000e+02", "P2: 7.1x"), "'P2' has a non-numeric"),
        (ODOMETRY_CALIB.replace("P2: 7.188560000000e+02 ", "P2: "), "'P2' has 11 values, expected 12"),
        (f"P2: {P2_ROW}\nTr: " + " ".join(["0"] * 12) + "\n", "'Tr' rotation is singular"),
        (f"P2: {' '.join(['0'] * 12)}\nTr: {IDENTITY_ROW}\n", "'P2' left 3×3 block is singular"),
        (f"P2: {P2_ROW}\nR0_rect: 1 0 0 0 1 0 0 0\nTr_velo_to_cam: {IDENTITY_ROW}\n", "'R0_rect' has 8"),
        ("", "missing 'P2:'"),
    ],
)
def test_calib_errors(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match) as exc:
        read_calib(path)
    assert_names(exc, path)


def test_missing_calib_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read calibration") as exc:
        read_calib(tmp_path / "calib.txt")
    assert_names(exc, tmp_path / "calib.txt")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", "'line 2' has 11 values"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", "'line 1' has non-finite"),
        ("1 0 0 0 0 1 0 0 0 0 1 zero\n", "'line 1' has a non-numeric"),
    ],
)
def test_pose_errors(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match) as exc:
        read_poses(path)
    assert_names(exc, path)


def test_scan_past_the_end_of_poses_names_the_file_and_the_frame(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3)
    write_poses(seq.root / "poses.txt", seq.cam_poses[:2])
    match = r"2 poses \(frames 0\.\.1\) but scan 000002\.bin is frame 2$"
    with pytest.raises(DatasetError, match=match) as exc:
        KittiSequence(seq.root)
    assert_names(exc, seq.root / "poses.txt")
    # Only scans past the end count: a copy of frame 1 alone reads line 1 of the same two-line file.
    for fid in ("000000", "000002"):
        (seq.root / "velodyne" / f"{fid}.bin").unlink()
    ks = KittiSequence(seq.root)
    np.testing.assert_allclose(ks.cam_poses, seq.cam_poses[1:2], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("content", [b"", b"\x89PNG\r\n\x1a\n garbage", b"not an image at all"])
def test_unreadable_image(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "000001.png"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match="unreadable image") as exc:
        read_image(path)
    assert_names(exc, path)


def test_missing_image(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="unreadable image") as exc:
        read_image(tmp_path / "000009.jpg")
    assert_names(exc, tmp_path / "000009.jpg")


def test_png16_rejects_colour_png(tmp_path: Path) -> None:
    path = tmp_path / "sem.png"
    write_image(path, np.zeros((3, 3, 3), np.uint8))
    with pytest.raises(DatasetError, match="16-bit mask") as exc:
        read_png16(path)
    assert_names(exc, path)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0.0\n0.1\nabc\n", "malformed timestamps"),
        ("0.0\n0.1\n", r"2 timestamps \(frames 0\.\.1\) but scan 000002\.bin is frame 2"),
        ("0.0 1\n0.1 1\n0.2 1\n", "2 columns"),
        ("0.0\nnan\n0.2\n", "non-finite"),
    ],
)
def test_malformed_times(tmp_path: Path, make_tiny_sequence, text: str, match: str) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3, with_images=False, with_labels=False)
    (seq.root / "times.txt").write_text(text)
    with pytest.raises(DatasetError, match=match) as exc:
        KittiSequence(seq.root)
    assert_names(exc, seq.root / "times.txt")


def test_sequence_structure_errors(tmp_path: Path, make_tiny_sequence) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        KittiSequence(tmp_path / "nope")
    seq = make_tiny_sequence(tmp_path, n_frames=2, with_images=False, with_labels=False)
    (seq.root / "calib.txt").unlink()
    with pytest.raises(DatasetError, match="cannot read calibration") as exc:
        KittiSequence(seq.root)
    assert_names(exc, seq.root / "calib.txt")
    for p in (seq.root / "velodyne").iterdir():
        p.unlink()
    with pytest.raises(DatasetError, match=r"no \.bin scans") as exc:
        KittiSequence(seq.root)
    assert "velodyne" in str(exc.value)
    (seq.root / "velodyne").rmdir()
    with pytest.raises(DatasetError, match="missing velodyne/"):
        KittiSequence(seq.root)


def test_writers_refuse_bad_data(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        write_scan(tmp_path / "a.bin", np.zeros((3, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        write_scan(tmp_path / "a.bin", np.full((1, 4), np.nan))
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        write_label(tmp_path / "a.label", [70000])
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        write_label(tmp_path / "a.label", [-1])
    with pytest.raises(ValueError, match=r"instance ids for .* must be 0\.\.65535"):
        write_label(tmp_path / "a.label", [10], [1 << 16])
    with pytest.raises(ValueError, match="do not match"):
        write_label(tmp_path / "a.label", [10, 11], [1])
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        write_image(tmp_path / "a.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        write_png16(tmp_path / "m.png", np.full((2, 2), 70000))
    with pytest.raises(ValueError, match="poses must be"):
        write_poses(tmp_path / "poses.txt", np.eye(4))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------ atomic writes
@pytest.mark.parametrize("fail_at", ["replace", "fsync"])
def test_failed_write_keeps_old_file_and_leaves_no_temp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fail_at: str
) -> None:
    path = tmp_path / "000000.label"
    write_label(path, [10, 40])
    before = path.read_bytes()

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, fail_at, boom)
    with pytest.raises(OSError, match="No space left"):
        write_label(path, [50, 50, 50])
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000000.label"]


def test_refused_label_write_keeps_old_file(tmp_path: Path) -> None:
    path = tmp_path / "000000.label"
    write_label(path, [10, 40])
    with pytest.raises(ValueError):
        write_label(path, [10, 1 << 20])
    np.testing.assert_array_equal(read_label(path), [10, 40])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000000.label"]


# ----------------------------------------------------------------------------------------- sequence
def test_sequence_reads_back_what_was_written(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3, n_points=50)
    ks = KittiSequence(seq.root)
    assert len(ks) == 3 and ks.frame_ids == seq.frame_ids
    assert ks.has_labels and ks.has_images and not ks.has_gt2d
    np.testing.assert_allclose(ks.cam_poses, seq.cam_poses, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ks.poses, lidar_poses(seq.cam_poses, seq.calib.Tr), atol=1e-12)
    np.testing.assert_allclose(ks.poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(ks.times, seq.times)
    assert isinstance(ks.calib, Calib)
    np.testing.assert_allclose(ks.calib.P2, seq.calib.P2, rtol=1e-12)
    for i, frame in enumerate(ks):
        assert frame.frame_id == seq.frame_ids[i]
        np.testing.assert_array_equal(frame.points, seq.points[i])
        expected = seq.semantic[i].astype(np.uint32) | (seq.instance[i].astype(np.uint32) << 16)
        np.testing.assert_array_equal(frame.labels, expected)
        assert frame.has_image and frame.has_labels
        np.testing.assert_array_equal(frame.image, seq.images[i])
        np.testing.assert_array_equal(frame.pose, ks.poses[i])
    with pytest.raises(IndexError):
        ks.frame(3)


def test_sequence_world_points_agree_across_frames(tmp_path: Path, make_tiny_sequence) -> None:
    """A LiDAR point seen from frame 2 lands where frame 0's camera chain says it does."""
    seq = make_tiny_sequence(tmp_path, n_frames=3, with_images=False, with_labels=False)
    ks = KittiSequence(seq.root)
    p = np.array([7.0, -1.0, 0.5, 1.0])
    tr = seq.calib.Tr
    # camera-0 world via KITTI's chain, then into frame 0's LiDAR frame.
    via_camera = np.linalg.inv(tr) @ np.linalg.inv(seq.cam_poses[0]) @ seq.cam_poses[2] @ tr @ p
    np.testing.assert_allclose(ks.poses[2] @ p, via_camera, atol=1e-12)


def test_frames_sort_numerically_without_zero_padding(tmp_path: Path, tiny_calib: Calib) -> None:
    root = tmp_path / "seq"
    for stem in ("0", "2", "10", "1"):
        write_scan(root / "velodyne" / f"{stem}.bin", np.full((1, 4), float(stem), np.float32))
    write_calib(root / "calib.txt", tiny_calib)
    write_poses(root / "poses.txt", np.tile(np.eye(4), (11, 1, 1)))
    ks = KittiSequence(root)
    assert ks.frame_ids == ["0", "1", "2", "10"]
    assert ks.frame_numbers == (0, 1, 2, 10)
    assert [float(f.points[0, 0]) for f in ks] == [0.0, 1.0, 2.0, 10.0]


def _keep_scans(root: Path, keep: set[str]) -> None:
    """Delete every scan, image and label file whose frame id is not in ``keep`` (calib, poses.txt and
    times.txt stay whole, as when a user copies a subset of a sequence)."""
    for folder in ("velodyne", "image_2", "labels"):
        for path in (root / folder).glob("*"):
            if path.stem not in keep:
                path.unlink()


def test_subset_with_gaps_takes_its_frames_lines_and_keeps_the_world(
    tmp_path: Path, make_tiny_sequence
) -> None:
    """Scans 3, 5 and 6 of an 8-line poses.txt / times.txt: each takes its own line, and the world frame
    stays the LiDAR frame of pose line 0, so poses equal the whole sequence's (not re-based on scan 3)."""
    seq = make_tiny_sequence(tmp_path, n_frames=8, n_points=20)
    whole = KittiSequence(seq.root)
    _keep_scans(seq.root, {"000003", "000005", "000006"})
    ks = KittiSequence(seq.root)
    assert ks.frame_ids == ["000003", "000005", "000006"]
    assert ks.frame_numbers == (3, 5, 6)
    assert [f.number for f in ks] == [3, 5, 6] and [f.index for f in ks] == [0, 1, 2]
    np.testing.assert_array_equal(ks.poses, whole.poses[[3, 5, 6]])
    np.testing.assert_allclose(ks.cam_poses, seq.cam_poses[[3, 5, 6]], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ks.times, seq.times[[3, 5, 6]], rtol=1e-12)
    assert not np.allclose(ks.poses[0], np.eye(4))
    np.testing.assert_array_equal(ks.frame(1).pose, whole.frame(5).pose)
    np.testing.assert_array_equal(ks.frame(1).points, whole.frame(5).points)


def test_scans_without_numeric_names_need_one_line_each(tmp_path: Path, tiny_calib: Calib) -> None:
    root = tmp_path / "seq"
    for k, stem in enumerate(("b", "a", "c")):
        write_scan(root / "velodyne" / f"{stem}.bin", np.full((1, 4), float(k), np.float32))
    write_calib(root / "calib.txt", tiny_calib)
    cam = np.tile(np.eye(4), (4, 1, 1))
    cam[:, 0, 3] = [10.0, 11.0, 12.0, 13.0]
    write_poses(root / "poses.txt", cam)
    with pytest.raises(DatasetError, match=r"4 poses but 3 scans \(scans without numeric names") as exc:
        KittiSequence(root)
    assert_names(exc, root / "poses.txt")
    write_poses(root / "poses.txt", cam[:3])
    ks = KittiSequence(root)
    assert ks.frame_ids == ["a", "b", "c"] and ks.frame_numbers == (0, 1, 2)
    # Line k goes to the k-th scan in name order; world = line 0.
    np.testing.assert_allclose(ks.cam_poses[:, 0, 3], [10.0, 11.0, 12.0])
    np.testing.assert_allclose(ks.poses[0], np.eye(4), atol=1e-12)


def test_two_scans_with_the_same_number_are_refused(tmp_path: Path, tiny_calib: Calib) -> None:
    root = tmp_path / "seq"
    for stem in ("0", "01", "1"):
        write_scan(root / "velodyne" / f"{stem}.bin", np.zeros((1, 4), np.float32))
    write_calib(root / "calib.txt", tiny_calib)
    with pytest.raises(DatasetError, match=r"scans 01\.bin and 1\.bin are both frame 1") as exc:
        KittiSequence(root)
    assert "velodyne" in str(exc.value)


def test_select_takes_frame_numbers(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=8, n_points=5, with_images=False, with_labels=False)
    _keep_scans(seq.root, {"000002", "000003", "000005", "000006"})
    ks = KittiSequence(seq.root)
    assert ks.select(None) == range(4)
    assert ks.select(range(2, 7)) == range(4)
    assert ks.select(range(3, 6)) == range(1, 3)  # frames 3 and 5 (4 is a gap)
    assert ks.select(range(5, 6)) == range(2, 3)
    for bad, match in [
        (range(4, 5), "^frames 4:5 select no frame: no scan is numbered"),
        (range(0, 3), r"out of range: the sequence has frames 2\.\.6"),
        (range(5, 8), "out of range"),
        (range(5, 5), "select no frame"),
        (range(2, 7, 2), "step 2"),
    ]:
        with pytest.raises(LeapError, match=match):
            ks.select(bad)


def test_optional_parts(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3, with_images=False, with_labels=False)
    (seq.root / "times.txt").unlink()
    write_image(seq.root / "image_2" / "000001.jpg", np.zeros((8, 8, 3), np.uint8))
    write_label(seq.root / "labels" / "000000.label", np.zeros(50, np.int64))
    ks = KittiSequence(seq.root)
    assert ks.times is None
    assert ks.has_images and not ks.has_labels
    assert [f.has_image for f in ks] == [False, True, False]
    assert [f.has_labels for f in ks] == [True, False, False]
    with pytest.raises(DatasetError, match="no image for frame 000000") as exc:
        _ = ks.frame(0).image
    assert "image_2" in str(exc.value)
    assert ks.frame(1).image.shape == (8, 8, 3)


def test_frame_label_count_mismatch_names_the_label_file(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=2, n_points=50)
    write_label(seq.root / "labels" / "000001.label", np.zeros(49, np.int64))
    ks = KittiSequence(seq.root)
    assert ks.frame(0).labels.shape == (50,)
    with pytest.raises(DatasetError, match="label count 49 != point count 50") as exc:
        _ = ks.frame(1).labels
    assert_names(exc, seq.root / "labels" / "000001.label")


def test_sequence_reads_nothing_per_frame_until_asked(tmp_path: Path, make_tiny_sequence) -> None:
    """Opening validates the structure only: a corrupt scan, label and image fail on access, not on open."""
    seq = make_tiny_sequence(tmp_path, n_frames=3)
    bad_scan = seq.root / "velodyne" / "000001.bin"
    bad_scan.write_bytes(b"\0" * 17)
    (seq.root / "labels" / "000002.label").write_bytes(b"\0" * 3)
    (seq.root / "image_2" / "000002.png").write_bytes(b"broken")
    ks = KittiSequence(seq.root)
    assert len(ks) == 3
    np.testing.assert_array_equal(ks.frame(0).points, seq.points[0])
    frame = ks.frame(1)
    with pytest.raises(DatasetError, match="not a multiple of 16") as exc:
        _ = frame.points
    assert_names(exc, bad_scan)
    with pytest.raises(DatasetError, match="multiple of 4"):
        _ = ks.frame(2).labels
    with pytest.raises(DatasetError, match="unreadable image") as exc:
        _ = ks.frame(2).image
    assert_names(exc, seq.root / "image_2" / "000002.png")


def test_frame_caches_its_arrays(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=1, with_images=False, with_labels=False)
    frame = KittiSequence(seq.root).frame(0)
    first = frame.points
    (seq.root / "velodyne" / "000000.bin").unlink()
    assert frame.points is first


def test_frame_counts_and_checks_labels_without_reading_the_scan(tmp_path: Path, make_tiny_sequence) -> None:
    """num_points comes from the scan's size (16 bytes a point), so labels are checked against the scan
    without its 16 bytes a point being read (evaluate reads only the labels of a run without the 3D-CN)."""
    seq = make_tiny_sequence(tmp_path, n_frames=2, n_points=37)
    frame = KittiSequence(seq.root).frame(0)
    assert scan_point_count(seq.root / "velodyne" / "000000.bin") == 37
    assert frame.num_points == 37
    assert frame.labels.shape == (37,)
    assert "points" not in frame.__dict__
    read = KittiSequence(seq.root).frame(1)
    assert read.points.shape == (37, 4)
    (seq.root / "velodyne" / "000001.bin").write_bytes(b"")  # the points already read are the count
    assert read.num_points == 37
    bad = seq.root / "velodyne" / "000000.bin"
    bad.write_bytes(b"\0" * 33)
    with pytest.raises(DatasetError, match="33 bytes is not a multiple of 16") as exc:
        scan_point_count(bad)
    assert_names(exc, bad)
    bad.write_bytes(b"\0" * 32)
    with pytest.raises(DatasetError, match="label count 37 != point count 2") as exc:
        _ = KittiSequence(seq.root).frame(0).labels
    with pytest.raises(DatasetError, match="cannot read scan") as exc:
        scan_point_count(tmp_path / "000404.bin")
    assert_names(exc, tmp_path / "000404.bin")


# ------------------------------------------------------------------------- edges the mutants found
def test_write_scan_stores_float32_whatever_the_input_dtype(tmp_path: Path) -> None:
    pts = np.array([[1.5, -2.0, 0.25, 0.5], [3.0, 4.0, 5.0, 0.0]], np.float64)
    write_scan(tmp_path / "a.bin", pts)
    assert (tmp_path / "a.bin").stat().st_size == 2 * 16  # 16 bytes a point, not 32
    np.testing.assert_array_equal(read_scan(tmp_path / "a.bin"), pts.astype(np.float32))


def test_16_bit_writers_take_65535_and_refuse_65536(tmp_path: Path) -> None:
    write_label(tmp_path / "a.label", [0xFFFF])
    np.testing.assert_array_equal(read_label(tmp_path / "a.label"), [0xFFFF])
    write_png16(tmp_path / "m.png", np.array([[0xFFFF]]))
    np.testing.assert_array_equal(read_png16(tmp_path / "m.png"), [[0xFFFF]])
    with pytest.raises(ValueError, match=r"semantic ids .* 0\.\.65535"):
        write_label(tmp_path / "b.label", [0x10000])
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        write_png16(tmp_path / "n.png", np.array([[0x10000]]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.label", "m.png"]


def test_write_poses_takes_3x4_rows_and_refuses_other_shapes(tmp_path: Path) -> None:
    rows = np.arange(24, dtype=np.float64).reshape(2, 3, 4)
    write_poses(tmp_path / "poses.txt", rows)
    np.testing.assert_array_equal(read_poses(tmp_path / "poses.txt")[:, :3], rows)
    for shape in ((2, 3, 3), (2, 3, 5), (2, 4, 3)):
        with pytest.raises(ValueError, match="poses must be"):
            write_poses(tmp_path / "bad.txt", np.zeros(shape))
    assert not (tmp_path / "bad.txt").exists()


def test_write_image_format_follows_the_suffix_png_without_one(tmp_path: Path) -> None:
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0] = 200
    write_image(tmp_path / "a.jpg", rgb)
    assert (tmp_path / "a.jpg").read_bytes()[:2] == b"\xff\xd8"  # JPEG, as the name says
    write_image(tmp_path / "noext", rgb)
    assert (tmp_path / "noext").read_bytes()[:4] == b"\x89PNG"
    np.testing.assert_array_equal(read_image(tmp_path / "noext"), rgb)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        write_image(tmp_path / "b.png", np.zeros((4, 6, 3), np.uint16))  # 16-bit colour is not what we store
    assert not (tmp_path / "b.png").exists()


def test_pose_source_and_missing_poses(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=2, with_images=False, with_labels=False)
    ks = KittiSequence(seq.root)
    assert ks.has_poses and ks.pose_source == "file" and ks.pose_lines == 2
    (seq.root / POSES_NOTE).write_text("{}")
    assert KittiSequence(seq.root).pose_source == "estimated"
    # Poses kept elsewhere (e.g. estimated beside a read-only dataset): read from there, the note beside them.
    other = tmp_path / "elsewhere" / "poses.txt"
    moved = seq.cam_poses.copy()
    moved[1, 0, 3] = 5.0
    write_poses(other, moved)
    ks = KittiSequence(seq.root, poses_path=other)
    assert ks.poses_path == other and ks.pose_source == "file"
    np.testing.assert_allclose(ks.cam_poses, moved, rtol=1e-12, atol=1e-15)
    (seq.root / "poses.txt").unlink()
    ks = KittiSequence(seq.root)
    assert not ks.has_poses and ks.pose_source == "missing" and ks.pose_lines is None
    for attr in ("poses", "cam_poses"):
        with pytest.raises(PosesMissingError, match="no poses") as exc:
            getattr(ks, attr)
        assert_names(exc, seq.root / "poses.txt")
    assert len(ks) == 2 and ks.frame(1).points.shape == (50, 4)  # the rest of the sequence still opens


def test_every_scan_past_the_end_of_poses_is_counted(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3, with_images=False, with_labels=False)
    write_poses(seq.root / "poses.txt", seq.cam_poses[:1])
    match = r"1 poses \(frames 0\.\.0\) but scan 000001\.bin is frame 1 \(and 1 more scans past the end\)$"
    with pytest.raises(DatasetError, match=match):
        KittiSequence(seq.root)


def test_images_are_found_by_suffix_in_any_case(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=3, with_images=False, with_labels=False)
    img = np.full((4, 4, 3), 9, np.uint8)
    write_image(seq.root / "image_2" / "000000.PNG", img)
    write_image(seq.root / "image_2" / "000001.jpeg", img)
    (seq.root / "image_2" / "000002.txt").write_text("not an image")
    ks = KittiSequence(seq.root)
    assert [f.has_image for f in ks] == [True, True, False]
    np.testing.assert_array_equal(ks.frame(0).image, img)


def test_frame_reads_its_2d_ground_truth(tmp_path: Path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path, n_frames=2, with_images=False, with_labels=False)
    sem = np.array([[0, 10], [40, 65535]], np.uint16)
    inst = np.array([[0, 1], [2, 3]], np.uint16)
    write_png16(seq.root / "gt2d" / "semantic" / "000001.png", sem)
    write_png16(seq.root / "gt2d" / "instance" / "000001.png", inst)
    ks = KittiSequence(seq.root)
    assert ks.has_gt2d
    np.testing.assert_array_equal(ks.frame(1).gt2d_semantic, sem)
    np.testing.assert_array_equal(ks.frame(1).gt2d_instance, inst)


def test_scan_non_finite_counts_points_not_values(tmp_path: Path) -> None:
    pts = np.zeros((4, 4), np.float32)
    pts[0, :2] = np.nan  # two bad values in one point
    pts[3, 3] = np.inf
    path = tmp_path / "000004.bin"
    path.write_bytes(pts.tobytes())
    with pytest.raises(DatasetError, match="2 points have non-finite"):
        read_scan(path)


def test_missing_png16(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="unreadable 16-bit mask PNG") as exc:
        read_png16(tmp_path / "000009.png")
    assert_names(exc, tmp_path / "000009.png")


def test_poses_with_bom_and_crlf(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    path.write_bytes(b"\xef\xbb\xbf" + b"1 0 0 0 0 1 0 0 0 0 1 0\r\n1 0 0 2 0 1 0 0 0 0 1 3\r\n")
    poses = read_poses(path)
    assert poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(poses[1, :3, 3], [2, 0, 3])


def test_poses_with_bytes_that_are_not_utf8_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    path.write_bytes(b"1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 \xff 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="'line 2' has a non-numeric") as exc:
        read_poses(path)
    assert_names(exc, path)


def test_the_first_two_scans_with_the_same_number_are_refused(tmp_path: Path, tiny_calib: Calib) -> None:
    root = tmp_path / "seq"
    for stem in ("0", "00", "1"):
        write_scan(root / "velodyne" / f"{stem}.bin", np.zeros((1, 4), np.float32))
    write_calib(root / "calib.txt", tiny_calib)
    with pytest.raises(DatasetError, match=r"scans 0\.bin and 00\.bin are both frame 0"):
        KittiSequence(root)


def test_calib_with_a_bom_before_its_p2_line(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_bytes(b"\xef\xbb\xbf" + f"P2: {P2_ROW}\nTr: {IDENTITY_ROW}\n".encode())
    assert read_calib(path).P2[0, 0] == pytest.approx(720.0)


def test_calib_with_a_comment_that_is_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    comment = "# calibrated by Müller\n".encode("latin-1")
    path.write_bytes(comment + f"P2: {P2_ROW}\nTr: {IDENTITY_ROW}\n".encode())
    assert read_calib(path).P2[0, 0] == pytest.approx(720.0)


def test_calib_accepts_a_camera_in_normalised_units(tmp_path: Path) -> None:
    """Focal lengths in image widths (det of the 3×3 block 0.25): small, but far from singular."""
    path = tmp_path / "calib.txt"
    path.write_text(f"P2: 0.5 0 0.5 0 0 0.5 0.5 0 0 0 1 0\nTr: {IDENTITY_ROW}\n")
    assert read_calib(path).P2[0, 0] == 0.5


def test_velo_to_cam_without_rectification_and_its_errors_name_the_key(tmp_path: Path) -> None:
    velo = np.hstack([AXIS_SWAP, [[0.1], [0.2], [0.3]]])
    path = tmp_path / "calib.txt"
    path.write_text(f"P2: {P2_ROW}\nTr_velo_to_cam: {' '.join(str(v) for v in velo.ravel())}\n")
    np.testing.assert_allclose(read_calib(path).Tr[:3], velo, atol=1e-12)  # no R0_rect: used as it is
    path.write_text(f"P2: {P2_ROW}\nTr_velo_to_cam: 1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="'Tr_velo_to_cam' has 11 values") as exc:
        read_calib(path)
    assert_names(exc, path)


def test_tracking_format_folds_r_rect_into_tr(tmp_path: Path) -> None:
    r_rect = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    velo = np.hstack([AXIS_SWAP, [[0.1], [0.2], [0.3]]])
    path = tmp_path / "0002.txt"
    path.write_text(
        f"P2: {P2_ROW}\nR_rect {' '.join(str(v) for v in r_rect.ravel())}\n"
        f"Tr_velo_cam {' '.join(str(v) for v in velo.ravel())}\n"
    )
    np.testing.assert_allclose(read_calib(path).Tr[:3], r_rect @ velo, atol=1e-12)


def test_singular_velo_to_cam_names_its_key(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(f"P2: {P2_ROW}\nTr_velo_to_cam: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(DatasetError, match="'Tr_velo_to_cam' rotation is singular"):
        read_calib(path)
