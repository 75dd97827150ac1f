import json
import math

import pytest
import torch

from poseflow_train import se3
from types import SimpleNamespace

import numpy as np

from poseflow_train.evaluate import errors, flow_times, rollout, summarise, symmetries, unobserved


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


def test_instances_the_ingest_could_not_observe_are_misses(tmp_path):
    # Scene 0: object 1 twice (one too hidden to score), object 5 once;
    # the shard holds only object 1's scorable instance.
    scene = tmp_path / "heldout" / "000000"
    scene.mkdir(parents=True)
    gts = {"0": [{"obj_id": 1}, {"obj_id": 1}, {"obj_id": 5}]}
    infos = {"0": [{"visib_fract": 0.8}, {"visib_fract": 0.05}, {"visib_fract": 0.6}]}
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    (scene / "scene_gt_info.json").write_text(json.dumps(infos))
    records = np.zeros(1, dtype=[("ids", "<u4", 4), ("visib_fract", "<f4")])
    records["ids"][0, 0], records["visib_fract"][0] = 1, 0.8
    shard = SimpleNamespace(info={"dataset": str(tmp_path / "elsewhere"), "split": "heldout"},
                            path=tmp_path / "heldout.obs", records=records)
    observations = SimpleNamespace(shards=[shard], object_index={1: 0, 5: 1})
    assert unobserved(observations, 0.1) == {5: 1}
    # Two observed instances of two samples each, all within 5 deg 5 cm, and
    # one missed instance: 4 of 6 samples.
    rot, trans = torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.tensor([0.5, 0.5, 0.5, 0.5])
    assert summarise(rot, trans, 1, 2)["acc_5deg_5cm"] == 66.67
    assert summarise(rot, trans, 0, 2)["acc_5deg_5cm"] == 100.0


def test_flow_times_are_the_sampler_stages_grids():
    # poseflow_geometry::flow::TimeGrid's closed forms (K = 5).
    assert flow_times(5) == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert flow_times(5, "quadratic") == pytest.approx([0.0, 0.36, 0.64, 0.84, 0.96, 1.0])
    with pytest.raises(ValueError, match="cosine"):
        flow_times(5, "cosine")


def test_a_rollout_on_either_grid_with_the_exact_field_lands_on_the_target():
    # The rectified flow's exact velocity toward one pose is constant along
    # the path, so Euler steps of any lengths reach it.
    target_r = se3.so3_exp(torch.tensor([[0.3, -1.2, 0.5]]))[0]
    target_p = torch.tensor([0.02, -0.01, 0.03])
    asked = []

    def velocity(condition, mask, r, p, t):
        asked.append(float(t[0]))
        return (se3.so3_log(r.transpose(-1, -2) @ target_r) / (1 - t[:, None]),
                (target_p - p) / (1 - t[:, None]))

    cfg = SimpleNamespace(translation_noise_std=0.05)
    for grid in ("uniform", "quadratic"):
        asked.clear()
        r, p = rollout(velocity, torch.zeros(1, 2, 4), None, cfg, 3, 5,
                       torch.Generator().manual_seed(0), grid)
        assert asked == pytest.approx(flow_times(5, grid)[:-1])
        assert torch.allclose(r[0], target_r.expand(3, 3, 3), atol=1e-4)
        assert torch.allclose(p[0], target_p.expand(3, 3), atol=1e-6)
