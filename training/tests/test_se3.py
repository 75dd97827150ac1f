"""The training geometry against the Rust geometry core's vectors."""

import json
from pathlib import Path

import torch

from poseflow_train import se3

VECTORS = json.loads((Path(__file__).resolve().parents[2] / "tests/vectors/se3_flow.json").read_text())


def mat(values):
    return torch.tensor(values, dtype=torch.float64).reshape(3, 3)


def vec(values):
    return torch.tensor(values, dtype=torch.float64)


def test_exp_matches_rust():
    for case in VECTORS["so3_exp"]:
        assert torch.allclose(se3.so3_exp(vec(case["omega"])), mat(case["rotation"]), atol=1e-12)


def test_log_inverts_exp_near_zero_and_pi():
    for case in VECTORS["so3_exp"]:
        omega = vec(case["omega"])
        log = se3.so3_log(mat(case["rotation"]))
        if omega.norm() < torch.pi - 1e-6:
            assert torch.allclose(log, omega, atol=1e-9), (log, omega)
        else:  # at pi the axis sign is free
            assert torch.allclose(se3.so3_exp(log), mat(case["rotation"]), atol=1e-9)


def test_flow_matches_rust():
    for case in VECTORS["flow"]:
        r0, p0, r1, p1 = mat(case["r0"]), vec(case["p0"]), mat(case["r1"]), vec(case["p1"])
        t = torch.tensor(case["t"], dtype=torch.float64)
        r_t, p_t = se3.interpolate(r0, p0, r1, p1, t)
        assert torch.allclose(r_t, mat(case["r_t"]), atol=1e-9)
        assert torch.allclose(p_t, vec(case["p_t"]), atol=1e-12)
        v_rot, v_pos = se3.target_velocity(r_t, p_t, r1, p1, t)
        assert torch.allclose(v_rot, vec(case["v_rot"]), atol=1e-8)
        assert torch.allclose(v_pos, vec(case["v_pos"]), atol=1e-9)
        r_next, p_next = se3.euler_step(r_t, p_t, v_rot, v_pos, case["dt"])
        assert torch.allclose(r_next, mat(case["r_next"]), atol=1e-8)
        assert torch.allclose(p_next, vec(case["p_next"]), atol=1e-9)


def test_uniform_rotations_are_rotations():
    r = se3.uniform_rotation((1000,), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(r @ r.transpose(-1, -2), eye.expand_as(r), atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(1000, dtype=torch.float64))


def test_align_recovers_a_rigid_motion_including_half_turns():
    g = torch.Generator().manual_seed(3)
    rotations = torch.cat([se3.uniform_rotation((30,), generator=g, dtype=torch.float64),
                           se3.so3_exp(torch.tensor([[torch.pi, 0.0, 0.0], [0.0, 0.0, 1e-9]], dtype=torch.float64))])
    points = torch.randn(32, 50, 3, generator=g, dtype=torch.float64)
    shift = torch.randn(32, 3, generator=g, dtype=torch.float64)
    moved = points @ rotations.transpose(1, 2) + shift[:, None]
    r, p = se3.align(points, moved)
    assert torch.allclose(r, rotations, atol=1e-9) and torch.allclose(p, shift, atol=1e-9)


def test_align_is_a_least_squares_fit_under_noise_and_always_a_rotation():
    g = torch.Generator().manual_seed(4)
    rotation = se3.uniform_rotation((16,), generator=g, dtype=torch.float64)
    points = torch.randn(16, 200, 3, generator=g, dtype=torch.float64)
    noisy = points @ rotation.transpose(1, 2) + 0.05 * torch.randn(16, 200, 3, generator=g, dtype=torch.float64)
    r, _ = se3.align(points, noisy)
    assert torch.rad2deg(se3.geodesic_angle(r, rotation)).max() < 2.0
    # Collinear points leave the rotation about the line free: still a rotation.
    line = torch.linspace(-1, 1, 20, dtype=torch.float64)[None, :, None] * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    r, _ = se3.align(line, line)
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64)[None], atol=1e-9)
    assert torch.allclose(torch.det(r), torch.ones(1, dtype=torch.float64))
