"""The dense team map's core: depth blobs (decimate, quantize, compress and back), keyframe
points, the voxel cloud and the floor band's occupancy grid, on a room whose geometry is exact."""

import struct

import cv2
import numpy as np
import pytest

from coop_slam.dense import depth_image
from coop_slam.dense.dense_cloud import place, voxel_filter
from coop_slam.dense.grid_files import write_grid
from coop_slam.dense.keyframe_points import points_cam
from coop_slam.dense.occupancy import OCCUPIED, UNKNOWN, OccupancyConfig, occupancy_grid
from coop_slam.evaluation.grid_score import grid_scores
from helpers import ROOM_HI_M, TABLE_HI_M, TABLE_LO_M, camera, looking_out_pose, room_depth_image

CAM = camera()


def _robot_views(centre=(2.5, 2.0), n=16, height_m=0.3, noise_m=0.005):
    """A ground robot turning on the spot: (T_room_cam, points_cam) of n keyframes."""
    views = []
    for k in range(n):
        T = looking_out_pose(2 * np.pi * k / n, centre, height=height_m)
        depth = room_depth_image(T, CAM, noise_m, seed=k)
        blob = depth_image.encode(depth_image.decimate(depth, 4), 0.01)
        views.append((T, points_cam(depth_image.decode(blob), CAM, 0.1, 6.0)))
    return views


def test_blob_round_trip_keeps_depth_within_half_a_step():
    depth = room_depth_image(looking_out_pose(0.3, (2.5, 2.0), 0.3), CAM, noise_m=0.005)
    small = depth_image.decimate(depth, 4)
    blob = depth_image.encode(small, 0.01)
    back = depth_image.decode(blob)
    assert back.depth_m.shape == (120, 160) and back.decimation == 4
    assert np.abs(back.depth_m - small.depth_m).max() <= 0.005 + 1e-6
    assert len(blob) < 12_000  # a radio's price: a few kB


def test_decimated_points_lie_on_the_surfaces_they_came_from():
    T = looking_out_pose(0.0, (2.5, 2.0), 0.3)  # looking along +x at the wall x = 5
    pts = points_cam(depth_image.decimate(room_depth_image(T, CAM), 4), CAM, 0.1, 10.0)
    room = pts @ T[:3, :3].T + T[:3, 3]
    on_wall = room[np.abs(room[:, 0] - ROOM_HI_M[0]) < 0.02]
    assert len(on_wall) > 0.3 * len(room)
    # A wrong principal point for the decimated image would tilt or shift these by centimetres.
    assert np.abs(on_wall[:, 0] - ROOM_HI_M[0]).max() < 5e-3


def test_decimation_takes_the_median_of_valid_pixels_and_drops_mostly_empty_blocks():
    depth = np.zeros((4, 8), np.float32)
    depth[:, :4] = [[1, 1, 1, 9], [1, 1, 1, 1], [1, 1, 2, 1], [1, 1, 1, 1]]
    depth[0, 4:] = [2.0, np.nan, 0, 0]  # 1 valid pixel of 16: too few
    small = depth_image.decimate(depth, 4)
    assert small.depth_m.tolist() == [[1.0, 0.0]]


@pytest.mark.parametrize(
    "blob, what",
    [
        (b"", "too short"),
        (b"XX" + bytes(20), "not a depth blob"),
        (struct.pack("<2sBf", b"D1", 4, 0.01) + bytes(20), "16-bit"),
    ],
)
def test_bad_blobs_are_named(blob, what):
    with pytest.raises(depth_image.DepthImageError, match=what):
        depth_image.decode(blob)


def test_voxel_filter_keeps_one_centroid_per_voxel_and_placing_follows_the_pose():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.26, 0.0, 0.0]], np.float32)
    assert voxel_filter(pts, 0.05) == pytest.approx(np.array([[0.02, 0.02, 0.02], [0.26, 0, 0]]))
    assert len(voxel_filter(pts, 0.05, min_points=2)) == 1
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    assert place([(T, pts)])[0].tolist() == pytest.approx([1.01, 2.01, 3.01])


def _truth(grid):
    """Cells a wall or the table's sides cross (occupied), inside the room and off the table
    (free)."""
    rows, cols = grid.shape
    x = grid.origin_xy_m[0] + np.arange(cols + 1) * grid.cell_m  # cell borders
    y = grid.origin_xy_m[1] + np.arange(rows + 1) * grid.cell_m

    def crossing(lo, hi, borders):  # cells whose span [b_i, b_i+1] meets [lo, hi]
        return (borders[1:] >= lo) & (borders[:-1] <= hi)

    occupied = np.zeros(grid.shape, bool)
    for lo, hi in ((np.zeros(3), ROOM_HI_M), (TABLE_LO_M, TABLE_HI_M)):
        in_x, in_y = crossing(lo[0], hi[0], x), crossing(lo[1], hi[1], y)
        for edge in (lo[0], hi[0]):
            occupied |= np.outer(in_y, crossing(edge, edge, x))
        for edge in (lo[1], hi[1]):
            occupied |= np.outer(crossing(edge, edge, y), in_x)
    xc, yc = (x[:-1] + x[1:]) / 2, (y[:-1] + y[1:]) / 2
    inside = np.outer((yc > 0) & (yc < ROOM_HI_M[1]), (xc > 0) & (xc < ROOM_HI_M[0]))
    table = np.outer(
        (yc > TABLE_LO_M[1]) & (yc < TABLE_HI_M[1]), (xc > TABLE_LO_M[0]) & (xc < TABLE_HI_M[0])
    )
    return occupied, inside & ~table & ~occupied


def test_grid_of_a_robot_turning_in_a_room_shows_its_walls_and_table():
    grid = occupancy_grid(_robot_views(), OccupancyConfig(max_range_m=6.0))
    scores = grid_scores(grid, *_truth(grid))
    assert scores.iou_occupied > 0.9 and scores.iou_free > 0.95
    assert scores.coverage_free > 0.9  # one robot turning sees all but the table's shadow


def test_grid_scores_fail_a_grid_off_by_a_few_cells():
    grid = occupancy_grid(_robot_views(n=8), OccupancyConfig(max_range_m=6.0))
    occupied, free = _truth(grid)
    shifted = np.roll(occupied, 3, axis=1), np.roll(free, 3, axis=1)
    assert grid_scores(grid, *shifted).iou_occupied < 0.5


def test_a_grid_follows_its_keyframes_when_the_graph_moves_them():
    views = _robot_views(n=8)
    yaw = np.array([[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], [0, 0, 1, 0], [0, 0, 0, 1]])
    moved = occupancy_grid([(yaw @ T, p) for T, p in views])
    before = occupancy_grid(views)
    # The same cells, turned by 90 degrees about z and shifted by 1 m along x.
    assert moved.shape == before.shape[::-1]
    assert (moved.cells == OCCUPIED).sum() == pytest.approx((before.cells == OCCUPIED).sum(), 0.05)


def test_nothing_seen_gives_one_unknown_cell_and_points_above_the_band_say_nothing():
    assert occupancy_grid([]).cells.tolist() == [[UNKNOWN]]
    high = np.array([[0.0, -2.0, 1.0]], np.float32)  # 2 m above a camera at 0.3 m
    grid = occupancy_grid([(looking_out_pose(0.0, (0.0, 0.0), 0.3), high)])
    assert not (grid.cells == OCCUPIED).any()


def test_grid_files_are_what_map_server_reads(tmp_path):
    grid = occupancy_grid(_robot_views(n=4))
    pgm, yaml_path = write_grid(grid, str(tmp_path))
    raw = open(pgm, "rb").read()
    header = raw.split(b"\n", 3)
    assert header[0] == b"P5" and header[1] == f"{grid.shape[1]} {grid.shape[0]}".encode()
    text = open(yaml_path).read()
    assert "image: grid.pgm" in text and "resolution: 0.050000" in text
    image = np.frombuffer(header[3], np.uint8).reshape(grid.shape)
    # The image's top row is the grid's last row (largest y).
    assert ((image[::-1] == 0) == (grid.cells == OCCUPIED)).all()


def test_rgbd_and_stereo_keyframes_bring_the_depth_they_saw_and_monocular_ones_none():
    from test_stereo import STEREO, _pair

    import helpers_vo
    from coop_slam.geometry import se3
    from coop_slam.vo.dense_depth import DenseDepthConfig, depth_image_blob

    config = DenseDepthConfig(stereo_max_baselines=40.0)  # the room is 24-31 baselines away
    planes = helpers_vo.room(np.random.default_rng(0))
    left, right, depth = _pair(planes, se3(t=[0.1, -0.1, 0.3]))
    gray = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
    truth = depth_image.decimate(depth, 8).depth_m
    for sensor, second, within in (
        ("rgbd", depth, 0.006),
        ("stereo", cv2.cvtColor(right, cv2.COLOR_BGR2GRAY), 0.03),
    ):
        blob = depth_image_blob(config, sensor, STEREO, gray, second, registered=True)
        got = depth_image.decode(blob)
        assert got.depth_m.shape == truth.shape == (60, 80), sensor
        both = (got.depth_m > 0) & (truth > 0)
        assert both.mean() > 0.6, sensor  # stereo: all but the left border and blank texture
        rel = np.abs(got.depth_m[both] - truth[both]) / truth[both]
        assert np.median(rel) < within, (sensor, np.median(rel))
    assert depth_image_blob(config, "mono", STEREO, gray, None, registered=True) == b""
    near = depth_image.decode(
        depth_image_blob(DenseDepthConfig(), "stereo", STEREO, gray, second, registered=True)
    )
    assert 0 < near.depth_m.max() <= 25 * STEREO.baseline_m  # stereo: 25 baselines by default
    assert depth_image_blob(config, "rgbd", STEREO, gray, depth, registered=False) == b""
    off = DenseDepthConfig(width_px=0)
    assert depth_image_blob(off, "rgbd", STEREO, gray, depth, registered=True) == b""


def test_keyframe_depth_images_are_made_beside_tracking_for_rgbd_and_stereo():
    """The depth image is made in a worker thread (issue #50: ~7 ms of an RGB-D keyframe's
    tracking); what the worker makes is what the frame's depth gives, a monocular camera none."""
    from concurrent.futures import Future

    from test_stereo import STEREO, _pair

    import helpers_vo
    from coop_slam.geometry import se3
    from coop_slam.vo.dense_depth import (
        DenseDepthConfig,
        KeyframeDepthImages,
        depth_image_blob,
        resolved,
    )

    config = DenseDepthConfig(stereo_max_baselines=40.0)
    left, right, depth = _pair(helpers_vo.room(np.random.default_rng(0)), se3(t=[0.1, 0, 0.3]))
    gray = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
    right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
    for sensor, second in (("rgbd", depth), ("stereo", right)):
        images = KeyframeDepthImages(config, sensor, STEREO, registered=True)
        try:
            pending = images.make(gray, second)
            assert isinstance(pending, Future), sensor
            expected = depth_image_blob(config, sensor, STEREO, gray, second, True)
            assert resolved(pending) == expected and len(expected) > 100, sensor
        finally:
            images.close()
    assert KeyframeDepthImages(config, "mono", STEREO, True).make(gray, None) == b""


def test_the_servers_dense_map_places_each_keyframes_depth_by_its_current_pose():
    """A robot's keyframes with room depth images: the server's dense map lies on the room's
    walls and its grid shows them; moved by the graph, the map moves with the keyframes."""
    from coop_slam.team.server import TeamServer
    from helpers import team_server_config, team_world

    _, _, kfs, vocab = team_world(n_keyframes=8)
    server = TeamServer(team_server_config(robots=[1]), vocab)
    for k, kf in enumerate(kfs):
        T = looking_out_pose(2 * np.pi * k / len(kfs), (2.5, 2.0), height=0.3)
        depth = room_depth_image(T, kf.camera, 0.005, seed=k)
        blob = depth_image.encode(depth_image.decimate(depth, 8), 0.01)
        kf.T_map_cam, kf.depth_image = T, np.frombuffer(blob, np.uint8)
        server.add_keyframe(kf)
    dense = server.dense_map_job()()
    assert dense.keyframes == len(kfs) and set(dense.robot_ids.tolist()) == {1}
    walls = (np.abs(dense.points[:, 0] - ROOM_HI_M[0]) < 0.03) | (np.abs(dense.points[:, 0]) < 0.03)
    walls |= (np.abs(dense.points[:, 1] - ROOM_HI_M[1]) < 0.03) | (
        np.abs(dense.points[:, 1]) < 0.03
    )
    assert walls.mean() > 0.3
    assert (dense.grid.cells == OCCUPIED).sum() > 200
    moved_by = np.eye(4)
    moved_by[0, 3] = 1.0  # the graph moves every keyframe 1 m along x
    pose_of = server.T_group_cam
    server.T_group_cam = lambda m, k: moved_by @ pose_of(m, k)
    moved = server.dense_map_job()()
    assert len(moved.points) == pytest.approx(len(dense.points), rel=0.01)
    assert np.median(moved.points[:, 0]) - np.median(dense.points[:, 0]) == pytest.approx(
        1.0, abs=0.03
    )
    assert moved.robot_grids == {}  # only when asked for
    server.config.dense.robot_grids = True
    own = server.dense_map_job()().robot_grids[1]  # robot 1's map is the world frame
    assert np.array_equal(own.cells, moved.grid.cells) and own.origin_xy_m == moved.grid.origin_xy_m
    server.config.dense.enabled = False
    assert server.dense_map_job() is None


def test_a_teammates_body_is_left_out_where_it_was_when_the_keyframe_saw_it():
    from coop_slam.dense.teammates import BodyTrack, outside_bodies
    from coop_slam.geometry import se3

    # A teammate driving along x at 1 m/s, keyframes at 0 and 2 s: at 1 s it is at x = 1.
    track = BodyTrack(
        2, 1, np.array([0.0, 2.0]), np.stack([se3(t=[0, 0, 0]), se3(t=[2, 0, 0])]), (0.4, 0.3, 0.5)
    )
    at_1s = track.box_at(1.0, max_gap_s=1.5, margin_m=0.1, reach_m=0.5)
    assert at_1s[0][:3, 3].tolist() == pytest.approx([1.0, 0.0, 0.0])
    assert track.box_at(-2.0, 1.5, 0.1, 0.5) is None  # before it started: not known
    T_parked, _, hi = track.box_at(9.0, 1.5, 0.1, 0.5)  # it stopped: where, or a little ahead
    assert T_parked[:3, 3].tolist() == [2.0, 0.0, 0.0] and hi[0] == pytest.approx(0.2 + 0.1 + 0.5)
    seen = np.array([[1.0, 0.1, 0.3], [1.0, 0.0, 0.7], [0.0, 0.0, 0.3], [1.25, 0.0, 0.1]])
    keep = outside_bodies(seen, [at_1s])
    # Its body (and 10 cm round it) goes; above it, and where it no longer is, stays.
    assert keep.tolist() == [False, True, True, False]


def _grid_points(T_room_cam, noise_m=0.003, seed=0):
    """A keyframe's decimated depth as an organized point grid (h, w, 3) in its camera frame."""
    image = depth_image.decimate(room_depth_image(T_room_cam, CAM, noise_m, seed), 8)
    small = image.camera(CAM)
    v, u = np.mgrid[0 : small.height, 0 : small.width]
    z = np.where(image.depth_m > 0, image.depth_m, np.nan)
    return np.stack([(u - small.cx) * z / small.fx, (v - small.cy) * z / small.fy, z], -1)


def test_depth_icp_registers_views_far_apart_and_refuses_a_lone_wall():
    from coop_slam.geometry import invert, se3, transform_error
    from coop_slam.registration.depth_icp import grid_normals, register_depth

    T_a = looking_out_pose(0.6, (1.5, 2.0), 1.0)
    T_b = looking_out_pose(1.3, (2.5, 1.5), 1.0)  # 40 deg apart: ORB would rarely match
    points_a, normals_a = grid_normals(_grid_points(T_a, seed=1))
    grid_b = _grid_points(T_b, seed=2)
    points_b = grid_b[np.isfinite(grid_b[..., 2])]
    truth = invert(T_a) @ T_b
    seed = se3(exp_so3_deg([0.0, 2.0, 0.0]), [0.05, -0.03, 0.04]) @ truth
    res = register_depth(points_a, normals_a, points_b, seed)
    assert res.accepted, res.reason
    dt, dr = transform_error(res.T_a_b, truth)
    assert dt < 0.005 and dr < 0.2, (dt, dr)
    assert 0 < res.sigma_trans_m < 0.02 and 0 < res.sigma_rot_deg < 1.0
    # The same view of a wall alone (points on one plane): it could slide along it.
    on_wall = np.abs(normals_a[:, 2]) < 2  # all
    wall = points_a[on_wall] * [1, 1, 0] + [0, 0, 2.0]
    lone = register_depth(wall, np.tile([0, 0, -1.0], (len(wall), 1)), wall[::2], np.eye(4))
    assert not lone.accepted and "direction" in lone.reason


def exp_so3_deg(deg_xyz):
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", deg_xyz, degrees=True).as_matrix()


def test_merged_robots_views_orb_cannot_match_are_linked_on_their_depth():
    """Two robots' keyframes of one room from 40 deg apart, with descriptors that match nothing:
    the overlap link falls back to their depth images and finds their relative pose; with depth
    links off there is no link."""
    from coop_slam.bow.database import DatabaseConfig
    from coop_slam.geometry import invert, transform_error
    from coop_slam.team.keyframe_store import KeyframeStore, stored_keyframe
    from coop_slam.team.overlap_links import OverlapLinkConfig, OverlapLinks
    from helpers import make_keyframe, team_vocabulary

    poses = {
        (1, 1): looking_out_pose(0.6, (1.5, 2.0), 1.0),
        (2, 1): looking_out_pose(1.3, (2.5, 1.5), 1.0),
    }
    records = []
    for seed, (map_id, kf_id) in enumerate(poses):
        rec = make_keyframe(n=300, robot_id=map_id, keyframe_id=kf_id, seed=seed)
        depth = room_depth_image(poses[map_id, kf_id], rec.camera, 0.003, seed)
        blob = depth_image.encode(depth_image.decimate(depth, 8), 0.01)
        rec.depth_image = np.frombuffer(blob, np.uint8)
        records.append(rec)
    store = KeyframeStore(team_vocabulary(records), DatabaseConfig())
    for rec in records:
        store.add(stored_keyframe(rec, rec.robot_id))
    # The team map's estimate: robot 2's keyframe 3 cm and 1 deg off.
    predicted = dict(poses)
    predicted[2, 1] = poses[2, 1] @ se3_about_z(1.0, [0.03, 0.0, 0.0])
    links = OverlapLinks(OverlapLinkConfig(), store, predicted.__getitem__)
    v = links.verify((1, 1), (2, 1), 0.0)
    assert v is not None and v.result.reason == "depth" and links.depth_verifications == 1
    dt, dr = transform_error(v.result.T_a_b, invert(poses[1, 1]) @ poses[2, 1])
    assert dt < 0.005 and dr < 0.2, (dt, dr)
    assert (
        OverlapLinks(OverlapLinkConfig(depth_max_m=0.0), store, predicted.__getitem__).verify(
            (1, 1), (2, 1), 0.0
        )
        is None
    )


def se3_about_z(deg, t):
    from coop_slam.geometry import se3

    return se3(exp_so3_deg([0.0, 0.0, deg]), t)
