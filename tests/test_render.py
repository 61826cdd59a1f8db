"""Previews on the CPU: the rasteriser against independent projections, and `jsr render` on a
results folder built here with a known room, a known box and known poses."""

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from jsr.cli import app
from jsr.export.colours import object_colour, rgb
from jsr.export.raster import MeshLayer, View, render_meshes
from jsr.export.render import (ObjectModel, load_objects, mesh_layer, placed, preview_view, recorded_view,
                               render_results, render_scene, spread_along_trajectory)
from jsr.geometry import make_transform, rotation_about_axis
from jsr.io.trajectory import write_tum_trajectory
from jsr.io.writers import write_csv, write_geometry_ply, write_json

INTRINSICS = {"fx": 200.0, "fy": 200.0, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240, "depth_scale": 5000.0}
ROOM_COLOUR = (0.7, 0.45, 0.3)  # brown: far from every object tint


def grid_mesh(corner, along_u, along_v, cells):
    """A flat ``cells x cells`` grid of triangles spanning ``corner + s u + t v`` (s, t in [0, 1])."""
    s, t = np.meshgrid(np.linspace(0, 1, cells + 1), np.linspace(0, 1, cells + 1))
    vertices = corner + s.reshape(-1, 1) * along_u + t.reshape(-1, 1) * along_v
    index = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return vertices, triangles


def test_rasteriser_matches_an_independent_fill_and_interpolates_depth():
    # A slanted plane in front of the camera: its pixels are those cv2.fillPoly gives, and the
    # depth at each pixel is where that pixel's ray meets the plane.
    vertices, triangles = grid_mesh(np.array([-0.6, -0.4, 1.5]), np.array([1.2, 0, 0.6]), np.array([0, 0.8, 0]), 6)
    view = View(160, 120, 100.0, 100.0, 79.5, 59.5, np.eye(4))
    layer = MeshLayer(vertices, triangles, np.full((len(vertices), 3), 0.5), label=3, cull_back_faces=False)
    rendering = render_meshes([layer], view, supersample=1)
    pixels, _ = view.project(vertices)
    expected = np.zeros((120, 160), np.uint8)
    for triangle in triangles:
        cv2.fillPoly(expected, [np.round(pixels[triangle] * 16).astype(np.int32)], 1, shift=4)
    drawn = rendering.labels == 3
    assert np.count_nonzero(drawn & (expected > 0)) / np.count_nonzero(drawn | (expected > 0)) > 0.97
    v, u = np.nonzero(drawn)
    rays = np.stack([(u - 79.5) / 100.0, (v - 59.5) / 100.0, np.ones(len(u))], 1)
    normal = np.cross([1.2, 0, 0.6], [0, 0.8, 0])
    depth_on_plane = (normal @ np.array([-0.6, -0.4, 1.5])) / (rays @ normal)
    np.testing.assert_allclose(rendering.depth[v, u], depth_on_plane, rtol=1e-5)
    assert np.all(rendering.color[~drawn] == 255)  # background stays white


def test_back_faces_are_culled_and_the_nearer_surface_wins():
    near, triangles = grid_mesh(np.array([-0.2, -0.2, 1.0]), np.array([0.4, 0, 0]), np.array([0, 0.4, 0]), 2)
    far, _ = grid_mesh(np.array([-1.5, -1.5, 2.0]), np.array([3.0, 0, 0]), np.array([0, 3.0, 0]), 2)
    view = View(100, 100, 80.0, 80.0, 49.5, 49.5, np.eye(4))
    grey = np.full((len(near), 3), 0.5)
    # these grids wind towards a camera at the origin; turned the other way, they are back faces
    culled = render_meshes([MeshLayer(near, triangles[:, ::-1], grey, 1)], view, supersample=1)
    assert not np.any(culled.labels)
    both = render_meshes([MeshLayer(far, triangles, grey, 2), MeshLayer(near, triangles, grey, 1)], view,
                         supersample=1)
    assert both.labels[50, 50] == 1 and both.labels[5, 5] == 2
    assert both.depth[50, 50] == pytest.approx(1.0) and both.depth[5, 5] == pytest.approx(2.0)


def test_viewpoints_spread_along_the_trajectory():
    poses = np.stack([make_transform(np.eye(3), [0.01 * i, 0, 0]) for i in range(101)])
    assert spread_along_trajectory(poses, 3) == [17, 50, 83]
    assert spread_along_trajectory(poses[:1], 3) == [0]


BOX_CENTRE_IN_OBJECT = np.array([0.3, -0.2, 1.1])  # the object frame's origin is the detecting camera, off the box


def make_results(root):
    """A results folder: a room (floor and back wall), a box moving on the floor, a camera
    sliding sideways; returns the true box poses ``T_w_o`` per frame and the camera poses."""
    floor_v, floor_t = grid_mesh(np.array([-2.0, 0.5, 0.5]), np.array([0, 0, 3.0]), np.array([4.0, 0, 0]), 20)
    wall_v, wall_t = grid_mesh(np.array([-2.0, -1.5, 3.5]), np.array([4.0, 0, 0]), np.array([0, 2.0, 0]), 20)
    o3d = __import__("open3d")
    room = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate([floor_v, wall_v])),
                                     o3d.utility.Vector3iVector(np.concatenate([floor_t, wall_t + len(floor_v)])))
    room.vertex_colors = o3d.utility.Vector3dVector(np.tile(ROOM_COLOUR, (len(floor_v) + len(wall_v), 1)))
    (root / "static").mkdir(parents=True)
    write_geometry_ply(root / "static" / "mesh.ply", room)
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.25)
    box.translate(BOX_CENTRE_IN_OBJECT - np.array([0.15, 0.1, 0.125]))
    box.vertex_colors = o3d.utility.Vector3dVector(np.full((len(box.vertices), 3), 0.7))
    (root / "objects" / "object_1").mkdir(parents=True)
    write_geometry_ply(root / "objects" / "object_1" / "mesh.ply", box)
    timestamps = 100.0 + np.arange(10) / 30.0
    cameras = np.stack([make_transform(rotation_about_axis([1, 0, 0], -0.25), [-0.3 + 0.06 * i, -0.4, 0.0])
                        for i in range(10)])
    # the box stands on the floor (y = 0.5 is the floor; y points down) at 2 m, then moves 40 cm
    on_floor = np.array([0.0, 0.5 - 0.125, 2.0]) - BOX_CENTRE_IN_OBJECT
    boxes = np.stack([make_transform(np.eye(3), on_floor + ([0.4, 0, 0] if i >= 6 else 0.0)) for i in range(10)])
    write_tum_trajectory(root / "camera.tum", timestamps, cameras)
    write_tum_trajectory(root / "objects" / "object_1" / "trajectory.tum", timestamps[2:], boxes[2:])
    write_tum_trajectory(root / "objects" / "object_1" / "keyframes.tum", timestamps[2:4],
                         np.linalg.inv(boxes[2:4]) @ cameras[2:4])
    write_csv(root / "landmarks.csv", ["frame", "timestamp", "map", "keyframes", "point_landmarks",
                                      "plane_landmarks", "tracked"],
              [[i, float(t), "static", 1, 10, 1, 1] for i, t in enumerate(timestamps)])
    write_json(root / "summary.json", {"status": "complete", "input": {"sequence": "nowhere", "intrinsics": INTRINSICS}})
    return boxes, cameras


def silhouette(vertices, triangles, view):
    """Pixels covered by the projected triangles (an independent fill, no depth test)."""
    pixels, depth = view.project(vertices)
    mask = np.zeros((view.height, view.width), np.uint8)
    for triangle in triangles:
        if np.all(depth[triangle] > 0):
            cv2.fillPoly(mask, [np.round(pixels[triangle] * 16).astype(np.int32)], 1, shift=4)
    return mask > 0


def test_object_pixels_are_where_the_placed_mesh_projects(tmp_path):
    boxes, cameras = make_results(tmp_path)
    static = mesh_layer(tmp_path / "static" / "mesh.ply", 1)
    (model,) = load_objects(tmp_path)
    assert isinstance(model, ObjectModel) and model.pose_at(100.0) is None  # not tracked before frame 2
    for frame in (4, 9):  # before and after the move
        timestamp = 100.0 + frame / 30.0
        view = recorded_view(cameras[frame], INTRINSICS)
        rendering, shown = render_scene(static, [model], timestamp, view, supersample=1)
        assert shown == [1]
        box = placed(model.layer, boxes[frame])
        expected = silhouette(box.vertices, box.triangles, view)
        drawn = rendering.labels == 2
        assert np.count_nonzero(expected) > 500
        # equal up to the pixels the outline passes through (the two fills round differently there)
        kernel = np.ones((3, 3), np.uint8)
        assert np.all(drawn[cv2.erode(expected.astype(np.uint8), kernel) > 0])
        assert not np.any(drawn[cv2.dilate(expected.astype(np.uint8), kernel) == 0])


def test_render_results_writes_the_previews(tmp_path):
    boxes, cameras = make_results(tmp_path)
    rendered = render_results(tmp_path, width=320)
    names = sorted(path.rsplit("/", 1)[1] for path in rendered["files"])
    assert names == ["object_1.png", "scene_frame_9.png", "static_view_1.png", "static_view_2.png",
                     "static_view_3.png"]
    assert rendered["frame"] == 9 and rendered["objects_placed"] == [1]
    for path in rendered["files"]:
        image = cv2.imread(path)
        assert image is not None and image.shape[1] == 320
        drawn = np.any(image < 245, axis=2)
        assert np.count_nonzero(drawn) > 0.05 * drawn.size, path  # not a blank image

    # The scene image: the box's pixels carry its tint, the room's do not.
    scene = cv2.imread(str(tmp_path / "plots" / "scene_frame_9.png"))[:, :, ::-1].astype(int)
    (model,) = load_objects(tmp_path)
    box_centre = boxes[9][:3, :3] @ model.centre + boxes[9][:3, 3]
    view = preview_view(cameras[9], box_centre, INTRINSICS, 320)
    box = placed(model.layer, boxes[9])
    inside = silhouette(box.vertices, box.triangles, view)
    inside = cv2.erode(inside.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # edges are blended
    inside[:40] = False  # under the caption band
    assert rgb(object_colour(1))[2] > rgb(object_colour(1))[0]  # a blue tint on a grey box, in a brown room
    blue = scene[..., 2] > scene[..., 0] + 10
    assert np.count_nonzero(inside) > 100
    assert np.mean(blue[inside]) > 0.9
    room = np.any(scene < 245, axis=2) & ~cv2.dilate(inside.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    room[:40] = False
    assert np.mean(blue[room]) < 0.05  # the label "object 1" is blue, and small


def test_cli_render_and_its_errors(tmp_path):
    make_results(tmp_path)
    runner = CliRunner()
    result = runner.invoke(app, ["render", str(tmp_path), "--width", "160", "--views", "1", "--frame", "3",
                                 "--out", str(tmp_path / "previews"), "--json", "-q"])
    assert result.exit_code == 0, result.output
    written = json.loads(result.stdout.strip().splitlines()[-1])
    assert written["frame"] == 3 and len(written["files"]) == 3
    assert (tmp_path / "previews" / "scene_frame_3.png").is_file()
    result = runner.invoke(app, ["render", str(tmp_path), "--frame", "12"])
    assert result.exit_code == 2 and "frame 12 was not processed" in result.output
    (tmp_path / "static" / "mesh.ply").unlink()
    result = runner.invoke(app, ["render", str(tmp_path)])
    assert result.exit_code == 2 and "static/mesh.ply" in result.output
