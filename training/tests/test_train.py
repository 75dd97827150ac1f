"""The correspondence loss: zero for the true coordinates and for those of
a symmetric twin, positive otherwise."""

import math

import torch

from poseflow_train import se3
from poseflow_train.model import ModelConfig
from poseflow_train.train import correspondence_loss


def test_correspondence_loss_is_zero_at_the_truth_and_at_a_symmetric_twin():
    cfg = ModelConfig(object_ids=[1])
    g = torch.Generator().manual_seed(0)
    rotation = se3.uniform_rotation((1,), generator=g)
    translation = torch.tensor([[0.01, -0.02, 0.0]])
    model_points = torch.randn(1, 64, 3, generator=g) * 0.03
    batch = {"rotation": rotation, "translation": translation, "object_index": torch.tensor([0]),
             "points": model_points @ rotation.transpose(1, 2) + translation[:, None]}
    half_turn = se3.so3_exp(torch.tensor([0.0, 0.0, math.pi]))
    table = (torch.stack([torch.eye(3), half_turn])[None], torch.zeros(1, 2, 3))
    assert correspondence_loss(model_points, batch, table, cfg).item() < 1e-5
    twin = model_points @ half_turn  # the coordinates under the turned ground truth
    assert correspondence_loss(twin, batch, table, cfg).item() < 1e-5
    identity_only = (torch.eye(3)[None, None], torch.zeros(1, 1, 3))
    assert correspondence_loss(twin, batch, identity_only, cfg).item() > 0.1
