"""The static transform tree shared by the bag reader and the nodes, and stamped poses placed by it."""

import numpy as np

from mosiv_ros.io.transforms import PoseStream, StaticTransforms, pose_at


def pose(yaw: float, t) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


def test_world_is_the_identity_even_with_no_transforms():
    np.testing.assert_array_equal(StaticTransforms().to_world("world"), np.eye(4))


def test_chain_resolves_up_and_down_a_tree_rooted_elsewhere():
    T_rig_world, T_rig_link, T_link_cam = pose(0.3, [1, 2, 3]), pose(-1.0, [0, 0.1, 0]), pose(2.0, [0.5, 0, 0])
    tree = StaticTransforms()
    tree.add("rig", "world", T_rig_world)  # world is a child: its edge is walked backwards
    tree.add("rig", "link", T_rig_link)
    tree.add("link", "cam", T_link_cam)
    expected = np.linalg.inv(T_rig_world) @ T_rig_link @ T_link_cam
    np.testing.assert_allclose(tree.to_world("cam"), expected, atol=1e-12)
    assert tree.frames == ["cam", "link", "rig", "world"]


def test_unreachable_frame_is_none_until_its_chain_arrives():
    tree = StaticTransforms()
    tree.add("link", "cam", pose(0.5, [0, 0, 1]))
    assert tree.to_world("cam") is None and tree.to_world("nowhere") is None
    tree.add("world", "link", pose(0.0, [1, 0, 0]))
    np.testing.assert_allclose(tree.to_world("cam")[:3, 3], [1, 0, 1], atol=1e-12)


def test_a_transform_published_again_replaces_the_old_one():
    tree = StaticTransforms()
    tree.add("world", "cam", pose(0.0, [1, 0, 0]))
    tree.add("world", "cam", pose(0.0, [0, 2, 0]))
    np.testing.assert_allclose(tree.to_world("cam")[:3, 3], [0, 2, 0])


def test_poses_received_before_their_frames_transform_are_placed_once_it_arrives_in_stamp_order():
    stream = PoseStream(StaticTransforms())
    stream.add(200, "base", pose(0.0, [0.1, 0, 0]))
    stream.add(100, "base", pose(0.5, [0.0, 0, 0]))
    stream.add(150, "elsewhere", pose(0.0, [0, 0, 0]))
    assert stream.world() == ([], ["base", "elsewhere"])
    T_world_base = pose(np.pi / 2, [1, 0, 0])
    stream.transforms.add("world", "base", T_world_base)
    poses, unreached = stream.world()
    assert [stamp for stamp, _ in poses] == [100, 200] and unreached == ["elsewhere"]
    np.testing.assert_allclose(poses[1][1], T_world_base @ pose(0.0, [0.1, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(poses[1][1][:3, 3], [1, 0.1, 0], atol=1e-12)
    stream.add(100, "world", pose(0.0, [0, 0, 2]))  # a pose at a stamp seen before replaces it
    np.testing.assert_allclose(stream.world()[0][0][1][:3, 3], [0, 0, 2])


def test_a_pose_between_samples_is_interpolated_the_short_way_and_held_exactly_at_the_ends():
    times = np.array([0.0, 1.0, 3.0])
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    half = np.sin(np.pi / 4), np.cos(np.pi / 4)  # a quarter turn about z
    # the last sample's quaternion has the other sign: the same rotation, the long way round
    quaternions = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, half[0], half[1]], [0.0, 0.0, -half[0], -half[1]]])
    position, q = pose_at(times, positions, quaternions, 0.5)
    np.testing.assert_allclose(position, [0.5, 0.0, 0.0])
    np.testing.assert_allclose(q, [0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)], atol=1e-12)  # an eighth turn
    position, q = pose_at(times, positions, quaternions, 2.0)  # the same rotation at both ends: no turn
    np.testing.assert_allclose(position, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(np.abs(q), np.abs(quaternions[1]), atol=1e-12)
    for t, k in ((-1.0, 0), (0.0, 0), (3.0, 2), (9.0, 2)):  # held, bit for bit
        position, q = pose_at(times, positions, quaternions, t)
        np.testing.assert_array_equal(position, positions[k])
        np.testing.assert_array_equal(q, quaternions[k])
