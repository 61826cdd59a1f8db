import cv2
import numpy as np
import pytest
import yaml

from jsr.errors import InputError
from jsr.io.camera import CAMERA_PRESETS, load_camera_yaml, resolve_intrinsics
from jsr.io.dataset import associate_timestamps, check_first_frame, open_sequence
from tests.helpers import colour_paths, write_tiny_tum


def test_associate_nearest_within_tolerance():
    colour = np.array([0.0, 0.033, 0.066, 0.100])
    depth = np.array([0.004, 0.031, 0.140, 0.101, 0.2])
    pairs = associate_timestamps(colour, depth, 0.02)
    # 0.066 has no depth within 0.02 s; 0.100 takes 0.101, not 0.140
    assert pairs == [(0, 0), (1, 1), (3, 3)]


def test_associate_is_one_to_one():
    pairs = associate_timestamps(np.array([0.0, 0.01]), np.array([0.005]), 0.02)
    assert len(pairs) == 1


def test_tum_sequence_loads_lazily_with_metres_and_rgb(tmp_path):
    root = write_tiny_tum(tmp_path / "seq", frames=5)
    sequence = open_sequence(root)
    assert len(sequence) == 5
    frame = sequence[2]
    assert frame.index == 2
    assert frame.timestamp == pytest.approx(100.0 + 2 / 30.0)
    assert frame.color.dtype == np.uint8 and frame.color.shape == (24, 32, 3)
    assert frame.depth.dtype == np.float32 and np.allclose(frame.depth, 1.5)
    # colour comes back as RGB: the file on disk is BGR
    on_disk = cv2.imread(str(frame.color_path))
    assert np.array_equal(frame.color, on_disk[:, :, ::-1])
    assert frame.name == frame.color_path.stem
    assert sequence.groundtruth is not None and len(sequence.groundtruth[0]) == 5
    assert sequence[-1].index == 4


def test_selection_start_stride_max_frames(tmp_path):
    root = write_tiny_tum(tmp_path / "seq", frames=10)
    sequence = open_sequence(root, start=1, stride=3, max_frames=2)
    assert len(sequence) == 2
    assert [round(t, 6) for t in sequence.timestamps] == [round(100 + 1 / 30, 6), round(100 + 4 / 30, 6)]
    with pytest.raises(InputError, match="past the last"):
        open_sequence(root, start=10)
    with pytest.raises(InputError):
        open_sequence(root, stride=0)


def test_missing_files_are_skipped_and_counted(tmp_path):
    root = write_tiny_tum(tmp_path / "seq", frames=6)
    colour_paths(root)[1].unlink()
    with (root / "rgb.txt").open("a") as stream:
        stream.write("500.0 rgb/500.000000.png\n")  # no depth near t = 500
    sequence = open_sequence(root)
    assert len(sequence) == 5
    assert sequence.report.missing_files == 1
    assert sequence.report.unmatched == 1
    assert sequence.report.listed == 7
    missing = colour_paths(write_tiny_tum(tmp_path / "whole", frames=6))[1].relative_to(tmp_path / "whole")
    assert any(str(missing) in note for note in sequence.report.notes)  # the note names the file


def test_depth_outside_range_becomes_invalid(tmp_path):
    root = write_tiny_tum(tmp_path / "seq", frames=2)
    sequence = open_sequence(root, max_depth=1.0)
    assert not np.any(sequence[0].depth > 0)


def test_image_set_with_subfolders(tmp_path):
    root = tmp_path / "set"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    for name in ("view_b", "view_a", "lonely"):
        cv2.imwrite(str(root / "color" / f"{name}.jpg"), np.zeros((24, 32, 3), np.uint8))
    for name in ("view_a", "view_b"):
        cv2.imwrite(str(root / "depth" / f"{name}.png"), np.full((24, 32), 5000, np.uint16))
    (root / "camera.yaml").write_text(yaml.safe_dump({"fx": 30, "fy": 30, "cx": 16, "cy": 12, "width": 32, "height": 24}))
    sequence = open_sequence(root)
    assert sequence.kind == "image-set"
    assert sequence.names == ["view_a", "view_b"]
    assert sequence.report.unmatched == 1
    assert np.allclose(sequence[1].depth, 1.0)


def test_image_set_with_name_tags(tmp_path):
    root = tmp_path / "flat"
    root.mkdir()
    for name in ("a", "b"):
        cv2.imwrite(str(root / f"{name}_rgb.png"), np.zeros((24, 32, 3), np.uint8))
        cv2.imwrite(str(root / f"{name}_depth.png"), np.full((24, 32), 5000, np.uint16))
    sequence = open_sequence(root, preset="primesense")
    assert len(sequence) == 2
    # the preset is 640x480, the images are not: loading a frame says so
    with pytest.raises(InputError, match="camera calibration"):
        sequence[0]


def test_camera_yaml_and_presets(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("fx: 500\nfy: 501\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\ndistortion: [0.1, 0, 0, 0, 0]\n")
    camera = load_camera_yaml(path)
    assert camera.fx == 500 and camera.depth_scale == 5000.0 and camera.has_distortion
    assert resolve_intrinsics(tmp_path, preset="TUM-FR3")[0] == CAMERA_PRESETS["tum-fr3"]
    with pytest.raises(InputError, match="unknown camera preset"):
        resolve_intrinsics(tmp_path, preset="kinect9")
    path.write_text("fx: 500\nfy: 501\ncx: 320\n")
    with pytest.raises(InputError, match="missing cy, width, height"):
        load_camera_yaml(path)
    path.write_text("fx: 500\nfy: 501\ncx: 320\ncy: 1\nwidth: 640\nheight: 480\nfocal: 3\n")
    with pytest.raises(InputError, match="unknown key"):
        load_camera_yaml(path)
    path.write_text("fx: 500\nfy: abc\ncx: 320\ncy: 1\nwidth: 640\nheight: 480\n")
    with pytest.raises(InputError, match="fy must be a number, got 'abc'"):  # the message names the key
        load_camera_yaml(path)
    path.write_text("fx: 500\nfy: 5\ncx: 320\ncy: 1\nwidth: 640\nheight: 480\ndistortion: 0.1\n")
    with pytest.raises(InputError, match="distortion must be a list"):
        load_camera_yaml(path)


def test_undistort_pixels_matches_opencv():
    camera = CAMERA_PRESETS["bonn"]
    pixels = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 450.0]])
    expected = cv2.undistortPoints(pixels.reshape(-1, 1, 2), camera.matrix, camera.distortion_coefficients, P=camera.matrix)
    assert np.allclose(camera.undistort_pixels(pixels), expected.reshape(-1, 2))
    # re-distorting the undistorted pixels gives the input back
    normalised = (camera.undistort_pixels(pixels) - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    points = np.column_stack([normalised, np.ones(len(pixels))])
    redistorted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.matrix, camera.distortion_coefficients)
    assert np.allclose(redistorted.reshape(-1, 2), pixels, atol=1e-3)


@pytest.mark.parametrize(
    "damage, fragment",
    [
        ("truncate_colour", "truncated"),
        ("empty_depth", "empty"),
        ("depth_size", "register depth to colour"),
        ("depth_8bit", "16-bit"),
    ],
)
def test_bad_frames_raise_one_line_errors(tmp_path, damage, fragment):
    root = write_tiny_tum(tmp_path / "seq", frames=2)
    colour = colour_paths(root)[0]
    depth = sorted((root / "depth").iterdir())[0]
    if damage == "truncate_colour":
        data = colour.read_bytes()
        colour.write_bytes(data[: len(data) // 3])
    elif damage == "empty_depth":
        depth.write_bytes(b"")
    elif damage == "depth_size":
        cv2.imwrite(str(depth), np.full((12, 16), 5000, np.uint16))
    elif damage == "depth_8bit":
        cv2.imwrite(str(depth), np.full((24, 32), 50, np.uint8))
    sequence = open_sequence(root)
    with pytest.raises(InputError) as error:
        sequence[0]
    assert fragment in str(error.value) and "\n" not in str(error.value)


def test_all_zero_depth_first_frame(tmp_path):
    root = write_tiny_tum(tmp_path / "seq", frames=2)
    for path in sorted((root / "depth").iterdir()):
        cv2.imwrite(str(path), np.zeros((24, 32), np.uint16))
    with pytest.raises(InputError, match="no valid depth"):
        check_first_frame(open_sequence(root))


def test_folder_problems(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_sequence(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="neither rgb.txt nor"):
        open_sequence(tmp_path / "empty")
    root = write_tiny_tum(tmp_path / "seq", frames=2)
    (root / "depth.txt").unlink()
    with pytest.raises(InputError, match="no depth.txt"):
        open_sequence(root)
    root = write_tiny_tum(tmp_path / "nocam", frames=2)
    (root / "camera.yaml").unlink()
    with pytest.raises(InputError, match="no camera.yaml"):
        open_sequence(root)
