"""Poses JSON parsing/validation and accumulation of several scans into the world frame."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.io import load_poses, read_scans
from hgca_testdata import refusal

# yaw +90 deg about z, then translate by (10, 0, 0): sensor (1, 0, 0) -> world (10, 1, 0)
YAW90 = [[0, -1, 0, 10], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
SHIFT = [[1, 0, 0, 0], [0, 1, 0, 5], [0, 0, 1, 2], [0, 0, 0, 1]]


def kitti(path, points, intensity):
    np.column_stack([points, intensity]).astype(np.float32).tofile(path)
    return path


@pytest.fixture
def two_scans(tmp_path):
    a = kitti(tmp_path / "a.bin", [[1, 0, 0], [0, 2, 0.5]], [0.1, 0.2])
    sub = tmp_path / "sweeps"
    sub.mkdir()
    b = kitti(sub / "b.bin", [[0, 0, 0], [1, 1, 1], [-3, 0, 0]], [0.3, 0.4, 0.5])
    return a, b


def write_json(path, doc):
    path.write_text(json.dumps(doc))
    return path


def test_json_poses_move_points_and_origins(tmp_path, two_scans):
    a, b = two_scans
    poses = write_json(tmp_path / "poses.json", {"scans": [
        {"file": "sweeps/b.bin", "pose": SHIFT, "origin": [0, 5, 3.8]},  # order differs from the scans
        {"file": "a.bin", "pose": YAW90},
    ]})
    scan = read_scans([a, b], poses=poses)
    np.testing.assert_allclose(scan.points, [[10, 1, 0], [8, 0, 0.5], [0, 5, 2], [1, 6, 3], [-3, 5, 2]],
                               atol=1e-6)
    np.testing.assert_array_equal(scan.attributes["scan_index"], [0, 0, 1, 1, 1])
    np.testing.assert_allclose(scan.attributes["intensity"], [0.1, 0.2, 0.3, 0.4, 0.5], rtol=1e-6)
    np.testing.assert_allclose(scan.origins, [[10, 0, 0], [0, 5, 3.8]])


def test_pose_list_in_file_order(two_scans):
    a, b = two_scans
    scan = read_scans([b, a], poses=[np.array(SHIFT), np.array(YAW90)])
    np.testing.assert_allclose(scan.points[3:], [[10, 1, 0], [8, 0, 0.5]], atol=1e-6)
    np.testing.assert_allclose(scan.origins, [[0, 5, 2], [10, 0, 0]])


def test_without_poses_points_stay_put(two_scans):
    a, b = two_scans
    scan = read_scans([a, b])
    np.testing.assert_allclose(scan.points[:2], [[1, 0, 0], [0, 2, 0.5]])
    np.testing.assert_array_equal(scan.origins, np.zeros((2, 3)))


def test_entry_for_another_folders_file_is_not_used(tmp_path, two_scans):
    """Another drive's `a.bin` (an entry with a folder part) must not place this `a.bin` (issue 11, item 6)."""
    a, _ = two_scans
    poses = write_json(tmp_path / "elsewhere.json", {"scans": [
        {"file": "/some/other/dir/a.bin", "pose": YAW90}, {"file": "unused.bin", "pose": SHIFT}]})
    with pytest.raises(InputError, match="no pose for scan") as exc:
        read_scans([a], poses=poses)
    assert "'/some/other/dir/a.bin' names a file of that name in another folder" in str(exc.value)


def test_bare_file_name_entry_matches_with_a_warning(tmp_path, two_scans):
    from hgca_core.errors import HgcaWarning

    a, _ = two_scans
    other = tmp_path / "poses_dir"
    other.mkdir()
    poses = write_json(other / "p.json", {"scans": [{"file": "a.bin", "pose": YAW90},
                                                    {"file": "unused.bin", "pose": SHIFT}]})
    with pytest.warns(HgcaWarning, match="by its file name alone"):
        scan = read_scans([a], poses=poses)
    np.testing.assert_allclose(scan.points[0], [10, 1, 0], atol=1e-6)


def test_entries_match_by_resolved_path(tmp_path, two_scans):
    """A scan given through a symlink or `..` finds the entry of the file it points to, without a warning."""
    import warnings

    a, b = two_scans
    link = tmp_path / "link_to_b.bin"
    link.symlink_to(b)
    poses = write_json(tmp_path / "p.json", {"scans": [{"file": "sweeps/b.bin", "pose": SHIFT},
                                                       {"file": "a.bin", "pose": YAW90}]})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scan = read_scans([link, tmp_path / "sweeps" / ".." / "a.bin"], poses=poses)
    np.testing.assert_allclose(scan.points[0], [0, 5, 2], atol=1e-6)
    np.testing.assert_allclose(scan.points[3], [10, 1, 0], atol=1e-6)


def test_load_poses_resolves_relative_paths(tmp_path):
    path = write_json(tmp_path / "p.json", {"scans": [{"file": "x/1.bin", "pose": SHIFT}]})
    (entry,) = load_poses(path)
    assert entry.path == str(tmp_path / "x" / "1.bin") and entry.origin is None
    np.testing.assert_array_equal(entry.pose, SHIFT)


def rot_x(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return [[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]]


@pytest.mark.parametrize("pose, problem", [
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "4x4"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
    ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "orthonormal"),
    ([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "reflection"),
    ([[1, 0, 0, "a"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "numbers"),
    ([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN"),
])
def test_bad_pose_rejected(tmp_path, pose, problem):
    path = tmp_path / "bad_poses.json"
    path.write_text(json.dumps({"scans": [{"file": "a.bin", "pose": pose}]}))
    assert "a.bin" in refusal(load_poses, path, problem)


def test_slightly_drifted_rotation_accepted(tmp_path):
    pose = np.array(rot_x(30), dtype=np.float32).astype(np.float64)  # float32-rounded rotation
    path = write_json(tmp_path / "ok.json", {"scans": [{"file": "a.bin", "pose": pose.tolist()}]})
    assert len(load_poses(path)) == 1


@pytest.mark.parametrize("doc, problem", [
    ("{not json", "not valid JSON"),
    ('[{"file": "a.bin"}]', '"scans" list'),
    ('{"scans": []}', '"scans" list'),
    ('{"scans": [{"pose": [[1]]}]}', '"file" string'),
    ('{"scans": [{"file": "a.bin"}]}', 'no "pose"'),
    ('{"scans": [{"file": "a.bin", "pose": %s, "origin": [1, 2]}]}' % json.dumps(SHIFT), '"origin"'),
    ('{"scans": [{"file": "a.bin", "pose": %s}, {"file": "./a.bin", "pose": %s}]}'
     % (json.dumps(SHIFT), json.dumps(SHIFT)), "same file"),
])
def test_bad_poses_documents(tmp_path, doc, problem):
    path = tmp_path / "broken.json"
    path.write_text(doc)
    refusal(load_poses, path, problem)


def test_scan_without_pose_entry(tmp_path, two_scans):
    a, b = two_scans
    poses = write_json(tmp_path / "only_a.json", {"scans": [{"file": "a.bin", "pose": YAW90}]})
    with pytest.raises(InputError, match="no pose for scan") as exc:
        read_scans([a, b], poses=poses)
    assert "only_a.json" in str(exc.value) and "b.bin" in str(exc.value)


def test_pose_list_count_mismatch(two_scans):
    a, b = two_scans
    with pytest.raises(InputError, match="1 poses given for 2 scans") as exc:
        read_scans([a, b], poses=[np.eye(4)])
    assert "a.bin" in str(exc.value) and "b.bin" in str(exc.value)


def test_missing_poses_file(tmp_path, two_scans):
    with pytest.raises(InputError, match="poses file not found") as exc:
        read_scans(two_scans, poses=tmp_path / "nope.json")
    assert "nope.json" in str(exc.value)


@pytest.mark.parametrize("kind, problem", [("folder", "is a folder"), ("loop", "symbolic link loop"),
                                           ("dangling", "symbolic link to a missing target"),
                                           ("deep", "nests arrays or objects too deeply")])
def test_poses_that_are_not_a_poses_file_say_what_they_are(tmp_path, two_scans, kind, problem):
    """A folder, a symlink loop or a dangling link is not "not found"; deep nesting is no RecursionError."""
    path = tmp_path / "poses.json"
    if kind == "folder":
        path.mkdir()
    elif kind == "loop":
        path.symlink_to(path)
    elif kind == "dangling":
        path.symlink_to(tmp_path / "gone.json")
    else:
        path.write_text('{"scans": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(InputError, match=problem) as exc:
        read_scans(two_scans, poses=path)
    assert "poses.json" in str(exc.value)


def test_no_scans():
    with pytest.raises(InputError, match="no scan files"):
        read_scans([])


def test_poses_json_after_a_byte_order_mark(tmp_path, two_scans):
    a, b = two_scans
    doc = {"scans": [{"file": "a.bin", "pose": SHIFT}, {"file": "sweeps/b.bin", "pose": YAW90}]}
    (tmp_path / "poses.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(doc).encode())
    plain = read_scans([a, b], poses=write_json(tmp_path / "plain.json", doc))
    np.testing.assert_array_equal(read_scans([a, b], poses=tmp_path / "poses.json").points, plain.points)
