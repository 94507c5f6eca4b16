"""TSDF fusion against analytically rendered depth of known shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from gear import _core
from gear.camera import Camera
from gear.mesh import tsdf_fuse
from gear.metrics import chamfer

RES = 64


def ring_cameras(n: int, radius: float = 1.6) -> list[Camera]:
    """Cameras on two latitude rings and the poles' neighbourhood, all looking at the origin."""
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = (0.6 if i % 2 else -0.5) + 0.2 * np.sin(3 * az)
        eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cams.append(Camera.look_at(eye, [0, 0, 0], [0, 0, 1], np.deg2rad(45), RES, RES))
    return cams


def render_spheres(cam: Camera, spheres: list[tuple[np.ndarray, float]]):
    """Exact camera-space z-depth and alpha of a union of spheres (nearest ray hit)."""
    j, i = np.mgrid[0:cam.height, 0:cam.width]
    dirs_cam = np.stack(
        [(i + 0.5 - cam.cx) / cam.fx, (j + 0.5 - cam.cy) / cam.fy, np.ones_like(i, float)], -1
    )  # z = 1, so the ray parameter is the camera-space depth itself
    c2w = cam.cam_to_world
    dirs = dirs_cam @ c2w[:3, :3].T
    eye = cam.center
    best = np.full(dirs.shape[:2], np.inf)
    for centre, r in spheres:
        oc = eye - centre
        a = np.sum(dirs * dirs, -1)
        b = 2 * np.sum(dirs * oc, -1)
        c = oc @ oc - r * r
        disc = b * b - 4 * a * c
        hit = disc >= 0
        t = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a), np.inf)
        best = np.minimum(best, np.where(t > 0, t, np.inf))
    alpha = np.isfinite(best).astype(np.float32)
    depth = np.where(np.isfinite(best), best, 0.0).astype(np.float32)
    return depth, alpha


def test_sphere_fusion_matches_true_surface():
    radius = 0.3
    cams = ring_cameras(12)
    # A small second sphere far from the first: a separate component the fusion must drop.
    spheres = [(np.zeros(3), radius), (np.array([0.0, 0.0, 0.55]), 0.06)]
    renders = [render_spheres(c, spheres) for c in cams]
    mesh = tsdf_fuse([d for d, _ in renders], [a for _, a in renders], cams,
                     voxel=0.01, trunc=0.03)
    assert len(mesh.faces) > 500
    verts = np.asarray(mesh.vertices)
    # Largest component only: every vertex on the big sphere (within a voxel), none near the
    # small one.
    r = np.linalg.norm(verts, axis=1)
    assert np.abs(r - radius).max() < 0.012
    assert np.linalg.norm(verts - spheres[1][0], axis=1).min() > 0.06
    # Outward orientation: positive enclosed volume close to the sphere's.
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * radius**3, rel=0.05)
    truth = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    # Sampling floor for two 10k-sample sets on this sphere's area is ~2·A/(π·n)·1000 ≈ 0.07;
    # a fused surface within ~2 mm adds little on top.
    assert chamfer(mesh, truth, n=10000, seed=0) < 0.1


def test_box_fusion_keeps_flat_faces():
    # A cube rendered by intersecting rays with its six slabs; the fused mesh's Chamfer distance
    # to the cube must be near the sampling floor, which shows corners and edges survive.
    half = 0.25
    cams = ring_cameras(10)
    depths, alphas = [], []
    for cam in cams:
        j, i = np.mgrid[0:RES, 0:RES]
        dirs = np.stack([(i + 0.5 - cam.cx) / cam.fx, (j + 0.5 - cam.cy) / cam.fy,
                         np.ones((RES, RES))], -1) @ cam.cam_to_world[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (-half - cam.center) / dirs
            t1 = (half - cam.center) / dirs
        near = np.max(np.minimum(t0, t1), -1)
        far = np.min(np.maximum(t0, t1), -1)
        hit = (near <= far) & (near > 0)
        depths.append(np.where(hit, near, 0).astype(np.float32))
        alphas.append(hit.astype(np.float32))
    mesh = tsdf_fuse(depths, alphas, cams, voxel=0.005, trunc=0.02)
    truth = trimesh.creation.box(extents=[2 * half] * 3)
    # Sampling floor on this cube (area 1.5): ~0.094; the rest allows a ~3 mm surface error.
    assert chamfer(mesh, truth, n=10000, seed=1) < 0.13
    assert mesh.volume == pytest.approx((2 * half) ** 3, rel=0.06)


def test_empty_and_masked_inputs_give_empty_mesh():
    cams = ring_cameras(3)
    zeros = [np.zeros((RES, RES), np.float32)] * 3
    assert len(tsdf_fuse(zeros, zeros, cams).faces) == 0
    # Depth present but alpha below the threshold everywhere: nothing is observed.
    depth, _ = render_spheres(cams[0], [(np.zeros(3), 0.3)])
    low = np.full((RES, RES), 0.4, np.float32)
    assert len(tsdf_fuse([depth], [low], cams[:1]).faces) == 0


def test_voxel_guard_coarsens_with_warning():
    cams = ring_cameras(6)
    renders = [render_spheres(c, [(np.zeros(3), 0.3)]) for c in cams]
    with pytest.warns(UserWarning, match="voxel"):
        mesh = tsdf_fuse([d for d, _ in renders], [a for _, a in renders], cams,
                         voxel=0.002, max_voxels=50**3)
    assert len(mesh.faces) > 100
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3).max() < 0.03


def test_bad_inputs_are_named():
    cams = ring_cameras(2)
    with pytest.raises(ValueError, match="2 depths, 1 alphas"):
        tsdf_fuse([np.zeros((RES, RES))] * 2, [np.zeros((RES, RES))], cams)
    with pytest.raises(ValueError, match=r"depths\[1\]"):
        tsdf_fuse([np.zeros((RES, RES)), np.zeros((3, 3))], [np.zeros((RES, RES))] * 2, cams)
    # NaN depth is treated as missing, never propagated.
    depth, alpha = render_spheres(cams[0], [(np.zeros(3), 0.3)])
    depth[::2] = np.nan
    mesh = tsdf_fuse([depth, depth], [alpha, alpha], cams, voxel=0.01, trunc=0.03)
    assert np.all(np.isfinite(mesh.vertices))


def test_generated_scene_depth_fuses_onto_its_gt_mesh(tmp_path):
    # Conventions check against the scene format: the generator's depth PNGs (camera-space z,
    # millimetres) and Blender-axis cameras, loaded by gear.data, must fuse onto its GT mesh.
    # At 48 px a pixel covers ~4 cm of the object, so silhouettes blur by about that much;
    # a wrong convention (ray length for z, flipped axes) would be off by decimetres.
    from scipy.spatial import cKDTree

    from gear.data import load_scene
    from gear.metrics import sample_surface
    from gear.synth import generate

    scene = load_scene(generate("fridge", tmp_path / "s", res=48, views=12, test_views=1),
                       splits=("train",))
    views = scene.train("end")
    mesh = tsdf_fuse([v.depth for v in views], [v.alpha for v in views],
                     [v.camera for v in views], voxel=0.01, trunc=0.03)
    gt = trimesh.load(scene.gt.meshes["end"]["whole"], force="mesh")
    dist, _ = cKDTree(sample_surface(gt, 100_000, 0)).query(sample_surface(mesh, 5000, 1))
    assert dist.mean() < 0.012  # fused surface on the GT surface (the GT's hidden inside aside)
    assert np.percentile(dist, 90) < 0.02
    np.testing.assert_allclose(mesh.bounds, gt.bounds, atol=0.05)  # the exterior is complete


def test_marching_cubes_only_on_fully_observed_cubes():
    # Observed slabs x = 0, 1 (outside, +1) and x = 2 (inside, -1); x >= 3 unobserved (+1 as
    # stored). The true surface lies at x = 1.5; the sign change between the observed x = 2 and
    # the unobserved x = 3 must not produce a second one at x = 2.5.
    from gear.mesh import _extract_surface

    volume = np.ones((6, 5, 5), np.float32)
    volume[2] = -1.0
    observed = np.zeros(volume.shape, bool)
    observed[:3] = True
    mesh = _extract_surface(volume, observed, lo=np.zeros(3), voxel=1.0)
    assert len(mesh.faces) > 0
    np.testing.assert_allclose(mesh.vertices[:, 0], 1.5)


def integrate_reference(centres: np.ndarray, views: list[tuple[np.ndarray, Camera]],
                        trunc: float) -> tuple[np.ndarray, np.ndarray]:
    """The projective TSDF update written with numpy, float32 op by op as the native one: per
    view, the voxels in front of the camera that project into the image onto a pixel with a
    positive depth d and lie less than `trunc` behind it add min((d - z) / trunc, 1)."""
    f = np.float32
    total = np.zeros(len(centres), f)
    count = np.zeros(len(centres), f)
    for depth, cam in views:
        m = cam.world_to_cam.astype(f)
        x, y, z = (m[r, 0] * centres[:, 0] + m[r, 1] * centres[:, 1] + m[r, 2] * centres[:, 2]
                   + m[r, 3] for r in range(3))
        with np.errstate(divide="ignore", invalid="ignore"):
            u = f(cam.fx) * x / z + f(cam.cx)
            v = f(cam.fy) * y / z + f(cam.cy)
        inside = (z > f(1e-6)) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        pixel = np.where(inside, v.astype(np.int64) * cam.width + u.astype(np.int64), 0)
        observed = depth.reshape(-1)[pixel]
        sdf = observed - z
        update = inside & (observed > 0) & (sdf >= -f(trunc))
        total += np.where(update, np.minimum(sdf / f(trunc), f(1)), f(0))
        count += update
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, total / count, f(0)), count


def test_native_integration_matches_the_numpy_reference():
    rng = np.random.default_rng(4)
    cams = ring_cameras(6)
    spheres = [(np.zeros(3), 0.3)]
    views = []
    for cam in cams:
        depth, _ = render_spheres(cam, spheres)
        depth[rng.random(depth.shape) < 0.1] = 0.0  # unobserved pixels
        views.append((depth, cam))
    centres = rng.uniform(-0.5, 0.5, (20000, 3)).astype(np.float32)
    trunc = 0.05
    distance, weight = _core.tsdf_integrate(
        centres, [d for d, _ in views], [c.world_to_cam.astype(np.float32) for _, c in views],
        [(c.fx, c.fy, c.cx, c.cy) for _, c in views], trunc)
    want_distance, want_weight = integrate_reference(centres, views, trunc)
    assert weight.dtype == distance.dtype == np.float32
    assert np.array_equal(weight, want_weight)
    assert 0.05 < (weight > 0).mean() < 0.95  # the test sees both observed and unobserved voxels
    np.testing.assert_allclose(distance, want_distance, rtol=0, atol=1e-6)


def test_native_integration_rejects_bad_inputs():
    cam = ring_cameras(1)[0]
    depth = np.ones((cam.height, cam.width), np.float32)
    args = ([depth], [cam.world_to_cam.astype(np.float32)], [(cam.fx, cam.fy, cam.cx, cam.cy)])
    centres = np.zeros((4, 3), np.float32)
    with pytest.raises(ValueError, match="trunc"):
        _core.tsdf_integrate(centres, *args, 0.0)
    with pytest.raises(ValueError, match="depths"):
        _core.tsdf_integrate(centres, [depth, depth], *args[1:], 0.1)
    with pytest.raises(ValueError):
        _core.tsdf_integrate(np.full((4, 3), np.nan, np.float32), *args, 0.1)
