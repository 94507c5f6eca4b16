"""Dual-quaternion kinematics against independent references (scipy rotations, matrix exp/log)."""

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation

from gear.articulation import PartMotion, extract_joint, joint_readings, resolve_ambiguous_joint
from gear.kinematics import (
    deform,
    dq_apply,
    dq_blend,
    dq_conj,
    dq_from_rt,
    dq_mul,
    dq_sclerp,
    dq_to_rt,
    quat_angle,
    quat_axis_angle,
    quat_from_axis_angle,
    quat_from_matrix,
    quat_mul,
    quat_normalize,
    quat_to_matrix,
)

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 2e-5, torch.float64: 1e-11}


def wxyz(rot: Rotation) -> np.ndarray:
    return np.roll(rot.as_quat(), 1, axis=-1)


def hinge_rt(axis, pivot, angle_deg):
    """R, t of a rotation by angle_deg about the line (pivot, axis)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    rot = Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix()
    return rot, np.asarray(pivot, float) - rot @ np.asarray(pivot, float)


def dq_of(rot, trans, dtype):
    q = torch.tensor(wxyz(Rotation.from_matrix(rot)), dtype=dtype)
    return dq_from_rt(q, torch.tensor(trans, dtype=dtype))


def homogeneous(rot, trans):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, trans
    return m


def random_motions(n, seed, max_deg=170.0):
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(5, max_deg, n)
    rots = Rotation.from_rotvec(np.deg2rad(angles)[:, None] * axes).as_matrix()
    return rots, rng.normal(size=(n, 3))


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_product_and_matrices_match_scipy(dtype):
    a, b = Rotation.random(20, random_state=1), Rotation.random(20, random_state=2)
    qa, qb = torch.tensor(wxyz(a), dtype=dtype), torch.tensor(wxyz(b), dtype=dtype)
    got = quat_to_matrix(quat_mul(qa, qb)).double().numpy()
    np.testing.assert_allclose(got, (a * b).as_matrix(), atol=TOL[dtype] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_from_matrix_including_half_turns(dtype):
    half_turns = Rotation.from_rotvec(
        np.pi
        * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]])
        / np.array([[1], [1], [1], [np.sqrt(2)]])
    )
    rots = np.concatenate([Rotation.random(30, random_state=3).as_matrix(), half_turns.as_matrix()])
    q = quat_from_matrix(torch.tensor(rots, dtype=dtype))
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(quat_to_matrix(q).double().numpy(), rots, atol=TOL[dtype] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_composition_and_inverse(dtype):
    rots, trans = random_motions(10, seed=4)
    a = dq_of(rots[:5], trans[:5], dtype)
    b = dq_of(rots[5:], trans[5:], dtype)
    pts = torch.randn(5, 3, dtype=dtype)
    np.testing.assert_allclose(
        dq_apply(*dq_mul(a, b), pts), dq_apply(*a, dq_apply(*b, pts)), atol=TOL[dtype] * 10
    )
    ident_r, ident_d = dq_mul(a, dq_conj(*a))
    np.testing.assert_allclose(ident_r.abs()[:, 0], np.ones(5), atol=TOL[dtype])
    np.testing.assert_allclose(ident_d, np.zeros((5, 4)), atol=TOL[dtype] * 10)
    np.testing.assert_allclose(dq_apply(*dq_conj(*a), dq_apply(*a, pts)), pts, atol=TOL[dtype] * 10)
    # Against homogeneous matrices.
    ref = np.einsum("nij,nj->ni", rots[:5], pts.double().numpy()) + trans[:5]
    np.testing.assert_allclose(dq_apply(*a, pts).double(), ref, atol=TOL[dtype] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sclerp_endpoints_and_screw_path_match_matrix_exp_log(dtype):
    rots, trans = random_motions(8, seed=5)
    qr, qd = dq_of(rots, trans, dtype)
    r0, d0 = dq_sclerp(qr, qd, 0.0)
    np.testing.assert_allclose(r0.abs()[:, 0], np.ones(8), atol=TOL[dtype])
    np.testing.assert_allclose(d0, np.zeros((8, 4)), atol=TOL[dtype])
    pts = torch.randn(8, 3, dtype=dtype)
    np.testing.assert_allclose(
        dq_apply(*dq_sclerp(qr, qd, 1.0), pts), dq_apply(qr, qd, pts), atol=TOL[dtype] * 10
    )
    for s in (0.25, 0.5, 0.8):
        got = dq_apply(*dq_sclerp(qr, qd, s), pts).double().numpy()
        for i in range(8):
            ref = scipy.linalg.expm(s * scipy.linalg.logm(homogeneous(rots[i], trans[i])).real)
            want = ref[:3, :3] @ pts[i].double().numpy() + ref[:3, 3]
            np.testing.assert_allclose(got[i], want, atol=TOL[dtype] * 50)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [0.0, 1e-6, 2.0, 60.0, 179.0])
def test_sclerp_swings_hinges_and_slides_prismatic(dtype, angle):
    axis, pivot = np.array([0.3, -0.2, 0.9]), np.array([0.5, 1.0, -0.4])
    axis /= np.linalg.norm(axis)
    rot, trans = hinge_rt(axis, pivot, angle)
    qr, qd = dq_of(rot, trans, dtype)
    on_axis = torch.tensor(np.stack([pivot, pivot + 0.7 * axis]), dtype=dtype)
    for s in (0.0, 0.3, 0.5, 1.0):
        r_s, d_s = dq_sclerp(qr, qd, s)
        assert torch.isfinite(r_s).all() and torch.isfinite(d_s).all()
        np.testing.assert_allclose(dq_apply(r_s, d_s, on_axis), on_axis, atol=TOL[dtype] * 20)
        assert float(quat_angle(r_s)) == pytest.approx(math.radians(s * angle), abs=1e-5)
    # A pure slide moves linearly.
    slide = dq_from_rt(
        torch.tensor([1.0, 0, 0, 0], dtype=dtype), torch.tensor([0.2, -1, 3], dtype=dtype)
    )
    _, t_half = dq_to_rt(*dq_sclerp(*slide, 0.5))
    np.testing.assert_allclose(t_half, [0.1, -0.5, 1.5], atol=TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_half_turn_and_double_cover(dtype):
    pivot = np.array([1.0, 2.0, 0.0])
    rot, trans = hinge_rt([0, 0, 1], pivot, 180.0)
    qr, qd = dq_of(rot, trans, dtype)
    pts = torch.randn(6, 3, dtype=dtype)
    # -q is the same motion, everywhere along the path for angles below 180 degrees.
    np.testing.assert_allclose(dq_apply(-qr, -qd, pts), dq_apply(qr, qd, pts), atol=TOL[dtype] * 10)
    rots, trans2 = random_motions(4, seed=6)
    r4, d4 = dq_of(rots, trans2, dtype)
    for s in (0.3, 0.7):
        np.testing.assert_allclose(
            dq_apply(*dq_sclerp(-r4, -d4, s), pts[:4]),
            dq_apply(*dq_sclerp(r4, d4, s), pts[:4]),
            atol=TOL[dtype] * 10,
        )
    # Halfway through a half turn: a quarter turn about the same hinge (either sense), pivot fixed.
    r_h, d_h = dq_sclerp(qr, qd, 0.5)
    assert float(quat_angle(r_h)) == pytest.approx(math.pi / 2, abs=1e-6)
    piv = torch.tensor(pivot, dtype=dtype)
    np.testing.assert_allclose(dq_apply(r_h, d_h, piv), piv, atol=TOL[dtype] * 10)
    joint = extract_joint(qr, qd, center=torch.zeros(3))
    assert joint["angle_deg"] == pytest.approx(180.0, abs=1e-3)
    assert abs(joint["axis"][2]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(joint["origin"], [1, 2, 0], atol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES)
def test_blend_aligns_signs_and_reproduces_identical_motions(dtype):
    rots, trans = random_motions(3, seed=7)
    qr, qd = dq_of(rots, trans, dtype)
    pts = torch.randn(5, 3, dtype=dtype)
    # The same motion three times, with mixed signs: the blend is that motion.
    same_r = torch.stack([qr[0], -qr[0], qr[0]])
    same_d = torch.stack([qd[0], -qd[0], qd[0]])
    w = torch.softmax(torch.randn(5, 3, dtype=dtype), dim=1)
    br, bd = dq_blend(same_r, same_d, w)
    np.testing.assert_allclose(
        dq_apply(br, bd, pts), dq_apply(qr[0], qd[0], pts), atol=TOL[dtype] * 10
    )
    # One-hot weights select a part.
    onehot = torch.nn.functional.one_hot(torch.tensor([0, 1, 2, 1, 0]), 3).to(dtype)
    br, bd = dq_blend(qr, qd, onehot)
    want = torch.stack([dq_apply(qr[k], qd[k], pts[i]) for i, k in enumerate([0, 1, 2, 1, 0])])
    np.testing.assert_allclose(dq_apply(br, bd, pts), want, atol=TOL[dtype] * 10)
    with pytest.raises(ValueError, match="weights"):
        dq_blend(qr, qd, torch.ones(5, 2, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_deform_moves_means_and_turns_gaussians(dtype):
    rot, trans = hinge_rt([1, 0, 0], [0, 0.5, 0], 90.0)
    motion = PartMotion.from_rt([(rot, trans)], dtype=dtype)
    qr, qd = (x.detach() for x in motion.motion())
    means = torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=dtype)
    quats = torch.tensor([[1.0, 0, 0, 0], [0, 0, 0, 1]], dtype=dtype)
    weights = torch.tensor([[1.0, 0], [0, 1]], dtype=dtype)
    new_means, new_quats = deform(means, quats, weights, qr, qd)
    np.testing.assert_allclose(new_means[0], means[0], atol=TOL[dtype])
    np.testing.assert_allclose(new_means[1].double(), rot @ [1, 1, 1] + trans, atol=TOL[dtype] * 10)
    np.testing.assert_allclose(new_quats[0], quats[0], atol=TOL[dtype])
    composed = Rotation.from_matrix(rot) * Rotation.from_quat([0, 0, 1, 0])
    np.testing.assert_allclose(
        quat_to_matrix(new_quats[1]).double(), composed.as_matrix(), atol=TOL[dtype] * 10
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [2.0, 60.0, 150.0])
def test_extract_joint_round_trip(dtype, angle):
    axis, pivot = np.array([0.0, 1.0, 1.0]) / np.sqrt(2), np.array([0.4, -0.3, 0.3])
    rot, trans = hinge_rt(axis, pivot, angle)
    center = np.array([1.0, 1.0, 0.0])
    joint = extract_joint(*dq_of(rot, trans, dtype), center)
    assert joint["type"] == "revolute"
    assert joint["angle_deg"] == pytest.approx(angle, abs=1e-3)
    np.testing.assert_allclose(joint["axis"], axis, atol=1e-5 if angle > 10 else 1e-3)
    # The origin lies on the hinge line and is its point closest to the centre.
    origin = np.array(joint["origin"])
    off = origin - pivot
    tol = 1e-4 if angle > 10 else 5e-3
    assert np.linalg.norm(off - off.dot(axis) * axis) < tol
    assert abs(np.dot(center - origin, axis)) < tol
    # Inverting the motion keeps the line and the angle (the axis flips).
    back = extract_joint(*dq_conj(*dq_of(rot, trans, dtype)), center)
    assert back["angle_deg"] == pytest.approx(angle, abs=1e-3)
    np.testing.assert_allclose(back["axis"], -axis, atol=1e-5 if angle > 10 else 1e-3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_extract_joint_prismatic(dtype):
    t = np.array([0.0, -0.3, 0.4])
    joint = extract_joint(*dq_of(np.eye(3), t, dtype), np.zeros(3))
    assert joint["type"] == "prismatic"
    assert joint["distance"] == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(joint["axis"], [0, -0.6, 0.8], atol=1e-6)
    still = extract_joint(*dq_of(np.eye(3), np.zeros(3), dtype), np.zeros(3), prismatic=True)
    assert still["distance"] == 0 and np.linalg.norm(still["axis"]) == pytest.approx(1.0)
    unturned = extract_joint(*dq_of(np.eye(3), t, dtype), np.zeros(3), prismatic=False)
    assert unturned["angle_deg"] == 0 and np.isfinite(unturned["origin"]).all()


def test_gradients_finite_at_identity_and_half_turn():
    for init in ([], [hinge_rt([0, 0, 1], [1, 0, 0], 180.0)]):
        motion = PartMotion.from_rt(init or [(np.eye(3), np.zeros(3))], dtype=torch.float32)
        means = torch.randn(50, 3)
        quats = torch.nn.functional.normalize(torch.randn(50, 4), dim=1)
        logits = torch.zeros(50, 2, requires_grad=True)
        loss = 0
        for s in (0.5, 1.0):
            qr, qd = motion.motion(s)
            m, q = deform(means, quats, torch.softmax(logits, 1), qr, qd)
            loss = loss + (m - means - 0.1).square().sum() + q.square().sum()
        loss.backward()
        for grad in (motion.qr.grad, motion.qd.grad, logits.grad):
            assert grad is not None and torch.isfinite(grad).all()
        assert motion.qd.grad.abs().sum() > 0


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.1, 60.0])
def test_sclerp_gradcheck(angle):
    rot, trans = hinge_rt([0.2, 0.5, -1.0], [0.3, 0.1, 0.2], angle)
    qr, qd = dq_of(rot, trans + np.array([0.0, 0.05, 0.1]), torch.float64)
    qr.requires_grad_(True)
    qd.requires_grad_(True)
    pts = torch.randn(4, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda r, d: dq_apply(*dq_sclerp(r, d, 0.4), pts), (qr, qd))


def test_part_motion_types_and_errors():
    rot, trans = hinge_rt([0, 1, 0], [0.2, 0, 0], 5.0)
    motion = PartMotion.from_rt([(rot, trans), (np.eye(3), [0, 0, 0.3])])
    qr, qd = (x.detach() for x in motion.motion(0.0))
    np.testing.assert_allclose(qr[:, 0], np.ones(3), atol=1e-6)
    np.testing.assert_allclose(qd, np.zeros((3, 4)), atol=1e-6)
    _, t_before = dq_to_rt(*(x[1].detach() for x in motion.motion()))
    motion.set_prismatic(1)
    qr, qd = (x.detach() for x in motion.motion())
    np.testing.assert_allclose(qr[1], [1, 0, 0, 0], atol=1e-7)
    np.testing.assert_allclose(dq_to_rt(qr[1], qd[1])[1], t_before, atol=1e-6)
    # A prismatic part's rotation gets no gradient.
    motion.qr.data[0] = torch.tensor([0.9, 0.1, 0.2, 0.0])
    qr, qd = motion.motion()
    qr.sum().backward()
    assert motion.qr.grad[0].abs().sum() == 0
    joints = motion.joints(np.zeros(3))
    assert [j["type"] for j in joints] == ["prismatic", "prismatic"]
    with pytest.raises(ValueError, match="part 0"):
        motion.set_prismatic(0)
    with pytest.raises(ValueError, match="num_parts"):
        PartMotion(0)
    with pytest.raises(ValueError, match="non-finite"):
        PartMotion.from_rt([(np.eye(3), [np.nan, 0, 0])])
    assert PartMotion(1).motion()[0].shape == (1, 4)


def resolve_by(motion, k, score, extra=()):
    """resolve_ambiguous_joint on the readings of part k, each scored by `score` in order."""
    readings = joint_readings(motion, k, extra)
    return resolve_ambiguous_joint(motion, k, readings, [score(c) for _, c in readings])


def test_resolve_ambiguous_joint_picks_lowest_score():
    true_rot, true_t = hinge_rt([0, 0, 1], [0.5, 0, 0], 170.0)
    stuck = hinge_rt([0, 0, 1], [0.5, 0, 0], 4.0)
    motion = PartMotion.from_rt([stuck])
    probe = torch.tensor([[1.0, 0.2, 0.0], [0.7, -0.4, 0.3]])
    target = torch.tensor(probe.numpy() @ true_rot.T + true_t)

    def score(candidate):  # stand-in for the photometric + depth loss
        qr, qd = (x.detach() for x in candidate.motion())
        return float((dq_apply(qr[1], qd[1], probe) - target).square().sum())

    chosen = resolve_by(motion, 1, score, extra=[(np.eye(3), true_t), (true_rot, true_t)])
    assert chosen.name == "revolute-extra1" and not bool(motion.prismatic[1])
    assert motion.joints(np.zeros(3))[0]["angle_deg"] == pytest.approx(170.0, abs=1e-3)
    # A drawer that picked up a spurious 4-degree twist: the slide keeping its translation wins.
    twisted = Rotation.from_rotvec([0, 0, np.deg2rad(4.0)]).as_matrix()
    motion = PartMotion.from_rt([(twisted, [0.3, 0.0, 0.0])])
    target = probe + torch.tensor([0.3, 0.0, 0.0])
    assert resolve_by(motion, 1, score).name == "prismatic"
    assert bool(motion.prismatic[1]) and score(motion) < 1e-10
    with pytest.raises(ValueError, match="non-finite"):
        resolve_by(motion, 1, lambda _: float("nan"))


def test_resolve_ambiguous_joint_keeps_the_tuned_winner():
    """A scorer that fine-tunes its candidate: the motion gets the tuned reading it scored."""
    motion = PartMotion.from_rt([hinge_rt([0, 0, 1], [0.5, 0, 0], 4.0)])
    tuned_t = torch.tensor([0.31, 0.02, 0.0])

    def tune_then_score(candidate):  # stands in for joint_types.motion_loss (tune, render)
        if bool(candidate.prismatic[1]):
            qr, qd = dq_of(np.eye(3)[None], tuned_t.numpy()[None], torch.float32)
            candidate.set_part(1, qr[0], qd[0], prismatic=True)
            return 0.0
        return 1.0

    assert resolve_by(motion, 1, tune_then_score).name == "prismatic"
    assert bool(motion.prismatic[1])
    joint = motion.joints(np.zeros(3))[0]  # the untuned slide would travel 0.035 along -y
    assert joint["distance"] == pytest.approx(float(tuned_t.norm()), abs=1e-5)


def test_deform_gradcheck():
    """Analytic gradients of the blended deformation match finite differences (float64)."""
    rot, trans = hinge_rt([0.3, 1.0, -0.2], [0.2, 0.1, 0.0], 75.0)
    qr, qd = dq_of(np.stack([np.eye(3), rot]), np.stack([np.zeros(3), trans]), torch.float64)
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(5, 3, dtype=torch.float64, generator=gen)
    quats = torch.nn.functional.normalize(torch.randn(5, 4, dtype=torch.float64, generator=gen))
    logits = torch.randn(5, 2, dtype=torch.float64, generator=gen)
    args = [x.clone().requires_grad_(True) for x in (means, quats, logits, qr, qd)]

    def run(m, q, lg, r, d):
        return deform(m, q, torch.softmax(lg, dim=1), r, d)

    assert torch.autograd.gradcheck(run, args)


def test_axis_angle_round_trips_with_the_sign_of_the_vector_part():
    rng = np.random.default_rng(4)
    q = quat_normalize(torch.as_tensor(rng.normal(size=(64, 4)), dtype=torch.float64))
    q[:8, 0] = -q[:8, 0].abs()  # turns past half a revolution about the vector part
    axis, angle = quat_axis_angle(q)
    assert torch.allclose(quat_from_axis_angle(axis, angle), q, atol=1e-12)
    assert bool(((angle >= 0) & (angle < 2 * math.pi)).all())
    assert torch.allclose((axis * q[:, 1:]).sum(-1), q[:, 1:].norm(dim=-1), atol=1e-12)
    still_axis, still_angle = quat_axis_angle(torch.tensor([1.0, 0.0, 0.0, 0.0]))
    assert torch.equal(still_axis, torch.zeros(3)) and float(still_angle) == 0.0
