"""Procedural objects, the rasteriser, ground truth and effects of generated scenes."""

import json

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from gear.camera import Camera
from gear.cli import main
from gear.data import load_scene, validate_scene
from gear.synth import EFFECTS, build, describe, generate, render_scene
from gear.synth.cameras import up_rotation
from gear.synth.generate import bounds, parse_up
from gear.synth.raster import rasterize
from gear.synth.render import pack

OBJECTS = [name for name, _ in describe()]


def _ray_cast_depth(vertices, faces, camera):
    """Reference z-depth by brute-force Moller-Trumbore ray casting (independent of the
    rasteriser): nearest hit along each pixel-centre ray, 0 for misses."""
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w]
    dirs_cam = np.stack(
        [
            (u.ravel() + 0.5 - camera.cx) / camera.fx,
            (v.ravel() + 0.5 - camera.cy) / camera.fy,
            np.ones(h * w),
        ],
        1,
    )
    c2w = camera.cam_to_world
    d = dirs_cam @ c2w[:3, :3].T  # camera z of a point at ray parameter s is s
    o = c2w[:3, 3]
    tri = vertices[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d[:, None, :], e2[None])
    det = np.einsum("rfk,fk->rf", p, e1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - tri[:, 0]
    bu = np.einsum("rfk,fk->rf", p, s) * inv
    q = np.cross(s, e1)
    bv = np.einsum("rk,fk->rf", d, q) * inv
    t = np.einsum("fk,fk->f", q, e2)[None] * inv
    hit = ok & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (t > 0)
    depth = np.where(hit, t, np.inf).min(1)
    return np.where(np.isfinite(depth), depth, 0.0).reshape(h, w)


def _point_triangle_distance(points, vertices, faces):
    """Exact distance from each point to the nearest triangle (brute force)."""
    tri = vertices[faces]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    best = np.full(len(points), np.inf)
    for chunk in np.array_split(np.arange(len(points)), max(1, len(points) // 256)):
        p = points[chunk][:, None, :]
        dist_plane = np.einsum("pfk,fk->pf", p - a, n)
        proj = p - dist_plane[..., None] * n
        inside = np.ones(dist_plane.shape, bool)
        for x, y in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("pfk,fk->pf", np.cross(y - x, proj - x), n) >= 0
        d = np.where(inside, np.abs(dist_plane), np.inf)
        for x, y in ((a, b), (b, c), (c, a)):
            seg = y - x
            t = np.clip(np.einsum("pfk,fk->pf", p - x, seg) / np.einsum("fk,fk->f", seg, seg), 0, 1)
            d = np.minimum(d, np.linalg.norm(p - (x + t[..., None] * seg), axis=-1))
        best[chunk] = d.min(1)
    return best


def test_rasteriser_matches_ray_casting():
    obj = build("storage7")
    packed = pack(obj, "end")
    center, radius = bounds(obj)
    rng = np.random.default_rng(3)
    for _ in range(2):
        direction = rng.normal(size=3)
        eye = center + 2.8 * radius * direction / np.linalg.norm(direction)
        cam = Camera.look_at(eye, center, [0, 0, 1], 0.7, 40, 32)
        got = rasterize(packed.vertices, packed.faces, cam).depth
        ref = _ray_cast_depth(packed.vertices, packed.faces, cam)
        # Coverage agrees except on a few pixel centres that graze an edge.
        assert ((got > 0) != (ref > 0)).mean() < 0.01
        both = (got > 0) & (ref > 0)
        close = np.abs(got[both] - ref[both]) < 1e-4 * ref[both]
        assert close.mean() > 0.98  # the rest: edge pixels where two surfaces meet


def test_list_and_objects_have_real_joints():
    assert {
        "fridge",
        "drawer_cabinet",
        "laptop",
        "box_lid",
        "oven",
        "storage7",
        "double_door",
        "safe180",
        "handle",
    } <= set(OBJECTS)
    assert len(build("storage7").parts) == 6
    assert build("drawer_cabinet").parts[0].joint.type == "prismatic"
    safe = build("safe180").parts[0].joint
    assert np.rad2deg(safe.end - safe.start) == pytest.approx(180.0)
    for name in OBJECTS:
        for part in build(name).parts:
            j = part.joint
            assert j.lower <= min(j.start, j.end) and max(j.start, j.end) <= j.upper
            assert j.start != j.end


@pytest.mark.parametrize("name", OBJECTS)
def test_object_renders_consistently(name, tmp_path):
    root = generate(name, tmp_path / name, res=48, views=4, test_views=1, seed=1)
    assert validate_scene(root) == []
    scene = load_scene(root)
    n_parts = len(build(name).parts) + 1
    seen = set()
    for v in scene.all_views():
        obj = v.alpha > 0
        assert obj.any()
        np.testing.assert_array_equal(v.depth > 0, obj)  # depth exactly where alpha
        np.testing.assert_array_equal(v.parts != 255, obj)  # a part id exactly where alpha
        assert v.parts[obj].max() < n_parts
        assert not (v.regions[~obj]).any()  # regions inside the object only
        assert (v.regions[obj] > 0).mean() > 0.7
        assert not v.rgb[~obj].any()  # clean background
        assert v.rgb[obj].std() > 0.02  # varied appearance, not a flat colour
        # Each region lies on one part (clean masks never cross a part boundary).
        for rid in np.unique(v.regions[v.regions > 0]):
            assert len(np.unique(v.parts[v.regions == rid])) == 1
        seen.update(np.unique(v.parts[obj]).tolist())
    assert 0 in seen and len(seen) >= 2


def _chamfer(a, b):
    return cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()


def test_trans_json_moves_start_meshes_onto_end_meshes(tmp_path):
    root = generate("storage7", tmp_path / "s7", res=32, views=1, test_views=0)
    scene = load_scene(root)
    assert len(scene.gt.joints) == 6
    for i, joint in enumerate(scene.gt.joints):
        start = trimesh.load(scene.gt.meshes["start"][f"part_{i}"], process=False)
        end = trimesh.load(scene.gt.meshes["end"][f"part_{i}"], process=False)
        moved = start.copy()
        moved.apply_transform(joint.motion())
        size = np.linalg.norm(end.extents)
        assert _chamfer(moved.vertices, end.vertices) < 1e-6 * size
        # And the joint really moves the part (the check above is not vacuous).
        assert _chamfer(start.vertices, end.vertices) > 1e-3 * size
    whole = trimesh.load(scene.gt.meshes["start"]["whole"], process=False)
    static = trimesh.load(scene.gt.meshes["end"]["static"], process=False)
    assert len(whole.faces) > len(static.faces) > 0


@pytest.mark.parametrize("name", [n for n in OBJECTS if n != "storage7"])
def test_gt_motion_of_every_object(name):
    obj = build(name)
    start, end = obj.gt_meshes("start"), obj.gt_meshes("end")
    for i, part in enumerate(obj.parts):
        motion = part.joint.gt().motion()
        moved = start[f"part_{i}"].vertices @ motion[:3, :3].T + motion[:3, 3]
        np.testing.assert_allclose(moved, end[f"part_{i}"].vertices, atol=1e-9)


def test_back_projected_depth_lands_on_gt_mesh(tmp_path):
    root = generate("storage7", tmp_path / "s7", res=64, views=2, test_views=0, seed=4)
    scene = load_scene(root)
    for state in ("start", "end"):
        mesh = trimesh.load(scene.gt.meshes[state]["whole"], process=False)
        size = np.linalg.norm(mesh.extents)
        pts = np.concatenate([v.camera.unproject(v.depth) for v in scene.train(state)])
        err = _point_triangle_distance(pts, mesh.vertices, mesh.faces)
        assert err.mean() < 0.005 * size
        assert np.median(err) < 0.001 * size


def test_seeded_and_deterministic(tmp_path):
    a = load_scene(generate("laptop", tmp_path / "a", res=32, views=2, test_views=0, seed=5))
    b = load_scene(generate("laptop", tmp_path / "b", res=32, views=2, test_views=0, seed=5))
    c = load_scene(generate("laptop", tmp_path / "c", res=32, views=2, test_views=0, seed=6))
    np.testing.assert_array_equal(a.train("end")[1].rgb, b.train("end")[1].rgb)
    assert not np.allclose(
        a.train("end")[1].camera.world_to_cam, c.train("end")[1].camera.world_to_cam
    )


def test_effects_change_only_their_channel(tmp_path):
    kw = dict(res=48, views=3, test_views=0, seed=2)
    clean = load_scene(generate("storage7", tmp_path / "clean", **kw))
    noisy = load_scene(generate("storage7", tmp_path / "fx", effects=",".join(EFFECTS), **kw))
    assert validate_scene(tmp_path / "fx") == []
    over = under = shine = 0
    for c, n in zip(clean.train("start"), noisy.train("start"), strict=True):
        np.testing.assert_array_equal(c.alpha, n.alpha)
        np.testing.assert_array_equal(c.parts, n.parts)
        obj = c.alpha > 0
        assert n.rgb[~obj].any()  # background
        assert not n.depth[~obj].any()  # noise never invents depth off the object
        kept = obj & (n.depth > 0)
        assert (n.depth[obj] == 0).mean() > 0.01  # dropouts
        rel = np.abs(n.depth[kept] / c.depth[kept] - 1)
        assert 0.001 < np.median(rel) < 0.02  # Gaussian noise of ~0.4%
        shine = max(shine, np.abs(n.rgb[obj] - c.rgb[obj]).max())
        parts_per_region = [
            len(np.unique(c.parts[(n.regions == r) & obj]))
            for r in np.unique(n.regions[n.regions > 0])
        ]
        under += max(parts_per_region) > 1
        over += len(np.unique(n.regions)) > len(np.unique(c.regions))
    assert under > 0 and over > 0
    assert shine > 0.05  # specular highlights somewhere


@pytest.mark.parametrize("up", ["+y", "-z", "0.3,-1,0.5"])
def test_rotated_world_is_the_same_capture_in_other_coordinates(up, tmp_path):
    """`up` rotates object, joints, cameras, light and solid texture together: every image is
    the one of the default (+z up) world, and the ground truth is the rotated one."""
    kw = dict(res=40, views=3, test_views=1, seed=3, effects=frozenset({"specular"}))
    obj = build("laptop", 3)
    plain = load_scene(render_scene(obj, tmp_path / "plain", **kw))
    turned = load_scene(render_scene(obj, tmp_path / "turned", up=up, **kw))
    assert validate_scene(tmp_path / "turned") == []
    up_vector = parse_up(up)
    rotation = up_rotation(up_vector)
    np.testing.assert_allclose(rotation @ [0, 0, 1], up_vector, atol=1e-12)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    differing = 0
    for a, b in zip(plain.all_views(), turned.all_views(), strict=True):
        np.testing.assert_allclose(b.camera.center, rotation @ a.camera.center, atol=1e-9)
        both = (a.alpha > 0) & (b.alpha > 0)
        # Float rounding may flip a pixel lying exactly on a triangle edge, nothing more.
        differing += int((a.alpha != b.alpha).sum() + (a.parts != b.parts).sum())
        np.testing.assert_allclose(b.rgb[both], a.rgb[both], atol=2e-3)
        np.testing.assert_allclose(b.depth[both], a.depth[both], rtol=1e-4)
    assert differing <= 2
    for ga, gb in zip(plain.gt.joints, turned.gt.joints, strict=True):
        np.testing.assert_allclose(gb.origin, rotation @ ga.origin, atol=1e-9)
        np.testing.assert_allclose(gb.axis, rotation @ ga.axis, atol=1e-9)
        assert gb.amount == pytest.approx(ga.amount)
    meta = json.loads((tmp_path / "turned" / "synth.json").read_text())
    np.testing.assert_allclose(meta["up"], up_vector)


def test_bad_up_axis_is_refused(tmp_path):
    for bad in ("up", "+w", "0,0,0", "1,2", "nan,0,1"):
        with pytest.raises(ValueError, match="up axis"):
            render_scene(build("handle", 0), tmp_path / "bad", res=16, views=1, test_views=0,
                         up=bad)


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    small = ["--res", "32", "--views", "2", "--test-views", "1"]
    assert main(["synth", "handle", "--out", str(out), *small, "--effects", "mask-jitter"]) == 0
    meta = json.loads((out / "synth.json").read_text())
    assert meta["object"] == "handle" and meta["effects"] == ["mask-jitter"]
    assert main(["check", str(out)]) == 0
    # Regenerating into a generated scene replaces it; a foreign folder is refused.
    one = ["--res", "32", "--views", "1", "--test-views", "0"]
    assert main(["synth", "handle", "--out", str(out), *one]) == 0
    assert len(load_scene(out).train("start")) == 1 and load_scene(out).test("start") == []
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["synth", "handle", "--out", str(tmp_path / "other")]) == 1
    assert main(["synth", "handle", "--out", str(out), "--effects", "sparkles"]) == 1
    assert main(["synth", "handle", "--out", str(out), *one, "--up=-y"]) == 0
    assert json.loads((out / "synth.json").read_text())["up"] == [0.0, -1.0, 0.0]
    assert main(["synth", "handle", "--out", str(out), *one, "--up", "sideways"]) == 1
    assert main(["synth", "--list"]) == 0
    assert "storage7" in capsys.readouterr().out
    assert torch.get_num_threads() >= 1
