import json
import math

import torch

from poseflow_train import se3
from poseflow_train.evaluate import errors, symmetries


def write_info(tmp_path, entry):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "models_info.json").write_text(json.dumps({"13": entry}))
    return symmetries(tmp_path / "models" / "models_info.json")[13]


def test_a_pose_turned_about_a_continuous_axis_scores_as_the_ground_truth(tmp_path):
    transforms = write_info(tmp_path, {"diameter": 160.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
    gt_r = se3.so3_exp(torch.tensor([0.3, -0.2, 0.5]))
    gt_p = torch.tensor([0.01, 0.0, 0.02])
    turned = gt_r @ se3.so3_exp(torch.tensor([0.0, 0.0, math.radians(137.3)]))
    rot, trans = errors(turned[None], gt_p[None], gt_r, gt_p, transforms)
    assert rot.item() <= 0.5 and trans.item() < 1e-4
    tilted = gt_r @ se3.so3_exp(torch.tensor([math.radians(20.0), 0.0, 0.0]))
    rot, _ = errors(tilted[None], gt_p[None], gt_r, gt_p, transforms)
    assert abs(rot.item() - 20.0) < 0.1


def test_an_offset_symmetry_axis_moves_the_translation(tmp_path):
    # A symmetry about a z axis through (10 mm, 0, 0): the half turn maps the
    # origin to (20 mm, 0, 0), so the turned pose's origin sits elsewhere.
    transforms = write_info(tmp_path, {"diameter": 50.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [10, 0, 0]}]})
    gt_r, gt_p = torch.eye(3), torch.zeros(3)
    half = se3.so3_exp(torch.tensor([0.0, 0.0, math.pi]))
    rot, trans = errors(half[None], torch.tensor([[0.02, 0.0, 0.0]]), gt_r, gt_p, transforms)
    assert rot.item() <= 0.5 and trans.item() < 0.05
