"""Does the velocity network follow a sample along an ambiguity? For each
observation, the true pose turned by theta about an object axis is handed
to the network as the current sample at time t, and the turn of the
predicted clean pose about the same axis is read off. For a view that
cannot tell those turns apart (a mug whose handle is hidden) an honest
field keeps the sample's turn at late t (gain 1); a field that pulls
every sample back to one pose (gain well below 1 at every step) collapses
the distribution once integrated finely, whatever the spread at few steps.

    python -m poseflow_train.diagnose --checkpoint checkpoints/lmo10-relative/checkpoint.pt \\
        --shard data/ambiguity-dev/mughidden.obs

prints one JSON object: per t, the median predicted turn for each theta
and the gain (slope of predicted against given turn, least squares)."""

import argparse
import json

import torch

from . import se3


def turn_about(rotation, axis, degrees):
    """rotation · exp(degrees · axis), per row of `rotation` [B,3,3];
    `degrees` a number or one per row."""
    angles = torch.deg2rad(torch.as_tensor(degrees, dtype=rotation.dtype)).reshape(-1, 1)
    return rotation @ se3.so3_exp(axis * angles)


def predicted_turns(clean_rotation, truth, axis):
    """Signed turn (degrees) about `axis` (object frame, unit) of
    truthᵀ · clean_rotation, per observation: the angle of the relative
    rotation's twist about the axis."""
    relative = truth.transpose(-1, -2) @ clean_rotation
    # The twist angle of R about a: atan2(a · vee(R − Rᵀ)/2, (tr R − (aᵀRa)) / 2).
    skew = 0.5 * (relative - relative.transpose(-1, -2))
    vee = torch.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1)
    along = (axis * vee).sum(-1)
    cos = 0.5 * (relative.diagonal(dim1=-2, dim2=-1).sum(-1) - (axis @ relative @ axis))
    return torch.rad2deg(torch.atan2(along, cos))


def gains(clean_pose, truth, translation, axis, thetas, times):
    """{t: {"turns": [median predicted turn per theta], "gain": slope}} for
    `clean_pose(rotation, translation, t) -> rotation` of a batch of
    observations whose true rotations are `truth`."""
    out = {}
    for t in times:
        medians = []
        for theta in thetas:
            turned = turn_about(truth, axis, theta)
            clean = clean_pose(turned, translation, torch.full((truth.shape[0],), t))
            medians.append(predicted_turns(clean, truth, axis).median().item())
        x = torch.tensor(thetas, dtype=torch.float64)
        y = torch.tensor(medians, dtype=torch.float64)
        slope = (((x - x.mean()) * (y - y.mean())).sum() / ((x - x.mean()) ** 2).sum()).item()
        out[str(t)] = {"turns": [round(v, 2) for v in medians], "gain": round(slope, 3)}
    return out


def main():
    from .data import Observations
    from .model import Encoder, ModelConfig, VelocityNet
    from .train import model_weights

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--shard", required=True, nargs="+")
    parser.add_argument("--axis", type=float, nargs=3, default=[0.0, 0.0, 1.0], help="object-frame axis (the mug's: z)")
    parser.add_argument("--thetas", type=float, nargs="+", default=[-60.0, -30.0, 0.0, 30.0, 60.0])
    parser.add_argument("--times", type=float, nargs="+", default=[0.4, 0.6, 0.8])
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    saved = torch.load(args.checkpoint, weights_only=False)
    cfg = ModelConfig(**saved["model_config"])
    encoder, velocity = Encoder(cfg).eval(), VelocityNet(cfg).eval()
    weights = model_weights(saved)
    encoder.load_state_dict(weights["encoder"])
    velocity.load_state_dict(weights["velocity"])
    observations = Observations(args.shard, cfg.object_ids, 0.1)
    batch = observations.batch(range(len(observations)))
    axis = torch.tensor(args.axis)
    axis = axis / axis.norm()
    with torch.no_grad():
        condition, mask = encoder(batch["image"], batch["token_mask"], batch["points"], batch["object_index"])
        result = gains(lambda r, p, t: velocity.clean_pose(condition, mask, r, p, t)[0], batch["rotation"],
                       batch["translation"], axis, args.thetas, args.times)
    print(json.dumps({"checkpoint": args.checkpoint, "step": saved["state"]["step"], "observations": len(observations),
                      "axis": args.axis, "thetas": args.thetas, "by_t": result}))


if __name__ == "__main__":
    main()
