"""SE(3) for flow matching, in PyTorch, with the conventions of the Rust
geometry core (shared/geometry; tests/vectors/se3_flow.json):

- rotations are 3x3 matrices R (batched as [..., 3, 3]), poses x_cam = R x + p;
- rotation vectors are axis * angle, angle in [0, pi];
- angular velocities are body-frame: R(t + dt) = R(t) exp(dt w);
- the path from (R0, p0) to (R1, p1): R_t = R0 exp(t log(R0^T R1)),
  p_t = (1 - t) p0 + t p1; target velocities w = log(R_t^T R1) / (1 - t),
  v = (p1 - p_t) / (1 - t).

Everything here is branch-free torch so it exports to ONNX.
"""

import math

import torch


def hat(w):
    """[..., 3] -> [..., 3, 3] skew-symmetric matrices."""
    zero = torch.zeros_like(w[..., 0])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )


def so3_exp(w):
    """Rodrigues' formula; series near zero."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(1e-24))
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    k = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a * k + b * (k @ k)


def quaternion_from_matrix(r):
    """Shepperd's method without branches: the four candidate formulas,
    the one with the largest pivot chosen by torch.where. Returns [..., 4]
    as (w, x, y, z) with w >= 0."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    pivots = torch.stack([trace, m00, m11, m22], -1)
    choice = pivots.argmax(-1, keepdim=True)

    def candidate(s, w, x, y, z):
        return torch.stack([w, x, y, z], -1) / s[..., None]

    s0 = 2.0 * torch.sqrt((1.0 + trace).clamp_min(1e-12))
    q0 = candidate(s0, 0.25 * s0 * s0, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1])
    s1 = 2.0 * torch.sqrt((1.0 + m00 - m11 - m22).clamp_min(1e-12))
    q1 = candidate(s1, r[..., 2, 1] - r[..., 1, 2], 0.25 * s1 * s1, r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0])
    s2 = 2.0 * torch.sqrt((1.0 - m00 + m11 - m22).clamp_min(1e-12))
    q2 = candidate(s2, r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 0.25 * s2 * s2, r[..., 1, 2] + r[..., 2, 1])
    s3 = 2.0 * torch.sqrt((1.0 - m00 - m11 + m22).clamp_min(1e-12))
    q3 = candidate(s3, r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1], 0.25 * s3 * s3)
    q = torch.where(choice == 0, q0, torch.where(choice == 1, q1, torch.where(choice == 2, q2, q3)))
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / q.norm(dim=-1, keepdim=True)


def so3_log(r):
    """Rotation vector with angle in [0, pi], exact near 0 and at pi (via the
    quaternion and atan2)."""
    q = quaternion_from_matrix(r)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    # angle / s -> 2 as s -> 0.
    scale = torch.where(s < 1e-7, 2.0 / q[..., :1].clamp_min(1e-12), angle / s.clamp_min(1e-12))
    return v * scale


def interpolate(r0, p0, r1, p1, t):
    """The path point at time t ([...]) between two batches of poses."""
    rel = so3_log(r0.transpose(-1, -2) @ r1)
    return r0 @ so3_exp(rel * t[..., None]), (1.0 - t[..., None]) * p0 + t[..., None] * p1


def target_velocity(r_t, p_t, r1, p1, t):
    """(v_rot, v_pos) that reach (r1, p1) at time 1 from (r_t, p_t) at t."""
    remaining = (1.0 - t)[..., None]
    return so3_log(r_t.transpose(-1, -2) @ r1) / remaining, (p1 - p_t) / remaining


def euler_step(r, p, v_rot, v_pos, dt):
    return r @ so3_exp(v_rot * dt), p + v_pos * dt


def uniform_rotation(shape, generator=None, dtype=torch.float32):
    """Haar-uniform rotations (Shoemake's uniform quaternion)."""
    u = torch.rand(*shape, 3, generator=generator, dtype=dtype)
    a, b = torch.sqrt(1.0 - u[..., 0]), torch.sqrt(u[..., 0])
    t2, t3 = 2 * math.pi * u[..., 1], 2 * math.pi * u[..., 2]
    q = torch.stack([b * torch.cos(t3), a * torch.sin(t2), a * torch.cos(t2), b * torch.sin(t3)], -1)
    return matrix_from_quaternion(q)


def matrix_from_quaternion(q):
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_from_6d(x):
    """Zhou et al.'s continuous 6D representation (two columns, Gram-Schmidt)."""
    a, b = x[..., :3], x[..., 3:]
    c1 = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    b = b - (c1 * b).sum(-1, keepdim=True) * c1
    c2 = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    c3 = torch.cross(c1, c2, dim=-1)
    return torch.stack([c1, c2, c3], -1)


def geodesic_angle(r1, r2):
    """Angle of r1^T r2 in radians, [0, pi]."""
    cos = (((r1.transpose(-1, -2) @ r2).diagonal(dim1=-2, dim2=-1).sum(-1)) - 1.0) / 2.0
    return torch.acos(cos.clamp(-1.0, 1.0))


def align(a, b, weights=None, squarings=10):
    """The rigid motion (R, p) minimising sum_i w_i |R a_i + p - b_i|^2 for
    point sets a, b [B, N, 3] (Horn's closed form: R from the dominant
    eigenvector of a 4x4 symmetric matrix). The eigenvector comes from
    repeated squaring, only matrix products, so this exports to ONNX where
    an SVD would not; the result is always a proper rotation. Ambiguous
    sets (collinear points, symmetric shapes) give one of the optimal
    rotations."""
    if weights is None:
        weights = torch.ones_like(a[..., 0])
    w = (weights / weights.sum(-1, keepdim=True).clamp_min(1e-12))[..., None]
    a_mean, b_mean = (w * a).sum(1), (w * b).sum(1)
    s = ((a - a_mean[:, None]) * w).transpose(1, 2) @ (b - b_mean[:, None])  # s[i, j] = sum a_i b_j
    sxx, sxy, sxz = s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]
    syx, syy, syz = s[:, 1, 0], s[:, 1, 1], s[:, 1, 2]
    szx, szy, szz = s[:, 2, 0], s[:, 2, 1], s[:, 2, 2]
    n = torch.stack(
        [
            torch.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
            torch.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
            torch.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
            torch.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1),
        ],
        -2,
    )
    # The eigenvalues of n lie within +-2 |s|_F: shifting by that makes the
    # wanted (largest) one also the largest in magnitude.
    eye = torch.eye(4, dtype=a.dtype, device=a.device)
    shift = 2.0 * s.pow(2).sum((-1, -2)).sqrt()[:, None, None] + 1e-12
    m = n + shift * eye
    for _ in range(squarings):
        m = m / m.abs().amax((-1, -2), keepdim=True).clamp_min(1e-30)
        m = m @ m
    # m ~ q q^T: its largest diagonal entry picks a column parallel to q.
    column = (m * eye).sum(-1).argmax(-1)
    q = torch.gather(m, 2, column[:, None, None].expand(-1, 4, 1))[..., 0]
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    r = matrix_from_quaternion(q)
    return r, b_mean - (r @ a_mean[..., None])[..., 0]
