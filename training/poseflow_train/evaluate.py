"""Sampling poses with the trained flow and scoring them: per-sample
n-degree m-cm accuracy (the paper's "None" selection), with the minimum
error over an object's discrete symmetries (models_info.json)."""

import json
import math
from pathlib import Path

import torch

from . import se3


# Continuous symmetries are discretised in steps of 1 degree (the rotation
# error is then at most 0.5 degrees above the exact minimum).
CONTINUOUS_STEPS = 360


def symmetries(dataset):
    """{obj_id: [(R [3,3], t [3] metres)]} with the identity first: the
    discrete symmetries, each combined with the discretised continuous ones
    (as the BOP toolkit does)."""
    path = Path(dataset) / "models" / "models_info.json"
    info = json.loads(path.read_text()) if path.exists() else {}
    out = {}
    for key, entry in info.items():
        discrete = [(torch.eye(3), torch.zeros(3))]
        for m in entry.get("symmetries_discrete", []):
            m = torch.tensor(m, dtype=torch.float32).reshape(4, 4)
            discrete.append((m[:3, :3], m[:3, 3] / 1000.0))
        continuous = [(torch.eye(3), torch.zeros(3))]
        for sym in entry.get("symmetries_continuous", []):
            axis = torch.tensor(sym["axis"], dtype=torch.float32)
            axis = axis / axis.norm()
            offset = torch.tensor(sym["offset"], dtype=torch.float32) / 1000.0
            for k in range(1, CONTINUOUS_STEPS):
                r = se3.so3_exp(axis * (2 * math.pi * k / CONTINUOUS_STEPS))
                continuous.append((r, offset - r @ offset))
        out[int(key)] = [(rd @ rc, rd @ tc + td) for rd, td in discrete for rc, tc in continuous]
    return out


@torch.no_grad()
def sample(encoder, velocity, batch, cfg, samples, steps, generator):
    """N samples per observation after K Euler steps from uniform rotations
    and Gaussian translations: ([B, N, 3, 3], [B, N, 3])."""
    condition, mask = encoder(batch["image"], batch["token_mask"], batch["points"], batch["object_index"])
    b = condition.shape[0]
    m = b * samples
    r = se3.uniform_rotation((m,), generator=generator)
    p = torch.randn(m, 3, generator=generator) * cfg.translation_noise_std
    for k in range(steps):
        t = torch.full((m,), k / steps)
        v_rot, v_pos = velocity(condition, mask, r, p, t)
        r, p = se3.euler_step(r, p, v_rot, v_pos, 1.0 / steps)
    return r.reshape(b, samples, 3, 3), p.reshape(b, samples, 3)


def errors(r, p, gt_r, gt_p, transforms):
    """Rotation (degrees) and translation (cm) errors of samples [N] against
    the closest symmetric version of the ground truth."""
    best_rot = torch.full((r.shape[0],), math.inf)
    best_trans = torch.full((r.shape[0],), math.inf)
    best_score = torch.full((r.shape[0],), math.inf)
    for s_r, s_t in transforms:
        sym_r, sym_p = gt_r @ s_r, gt_r @ s_t + gt_p
        rot = torch.rad2deg(se3.geodesic_angle(r, sym_r.expand_as(r)))
        trans = (p - sym_p).norm(dim=-1) * 100.0
        score = rot / 10.0 + trans / 5.0
        better = score < best_score
        best_rot, best_trans, best_score = (torch.where(better, a, b) for a, b in ((rot, best_rot), (trans, best_trans), (score, best_score)))
    return best_rot, best_trans


def validate(encoder, velocity, observations, cfg, count, samples, steps, seed):
    """Per-sample accuracies over the first `count` observations."""
    encoder.eval()
    velocity.eval()
    generator = torch.Generator().manual_seed(seed)
    transforms = symmetries(observations.info["dataset"])
    rots, transs = [], []
    for start in range(0, min(count, len(observations)), 16):
        batch = observations.batch(range(start, min(start + 16, count, len(observations))))
        r, p = sample(encoder, velocity, batch, cfg, samples, steps, generator)
        for i in range(r.shape[0]):
            sym = transforms.get(int(batch["obj_id"][i]), [(torch.eye(3), torch.zeros(3))])
            rot, trans = errors(r[i], p[i], batch["rotation"][i], batch["translation"][i], sym)
            rots.append(rot)
            transs.append(trans)
    encoder.train()
    velocity.train()
    rot, trans = torch.cat(rots), torch.cat(transs)

    def acc(deg, cm):
        return round(100.0 * ((rot < deg) & (trans < cm)).float().mean().item(), 2)

    return {
        "observations": len(rots),
        "samples": samples,
        "steps": steps,
        "acc_5deg_5cm": acc(5, 5),
        "acc_10deg_5cm": acc(10, 5),
        "acc_10deg_2cm": acc(10, 2),
        "median_rot_deg": round(rot.median().item(), 2),
        "median_trans_cm": round(trans.median().item(), 2),
    }


