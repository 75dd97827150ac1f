"""Training pieces: the correspondence loss (zero for the true coordinates
and a symmetric twin), hint paths, the refiner and pose perturbation."""

import math

import pytest
import torch

from poseflow_train import se3
from poseflow_train.model import ModelConfig
from poseflow_train.train import correspondence_loss, flow_batch


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


def test_hint_paths_end_at_the_coarse_pose_with_the_truth_as_target():
    cfg = ModelConfig(object_ids=[1])
    g = torch.Generator().manual_seed(0)
    truth_r = se3.uniform_rotation((2,), generator=g)
    hint_r = se3.uniform_rotation((2,), generator=g)
    batch = {"rotation": truth_r, "translation": torch.zeros(2, 3)}
    hint = (hint_r, torch.full((2, 3), 0.02))
    plain = flow_batch(batch, cfg, 64, 5, torch.Generator().manual_seed(1))
    mixed = flow_batch(batch, cfg, 64, 5, torch.Generator().manual_seed(1), hint, 0.5)
    always = flow_batch(batch, cfg, 64, 5, torch.Generator().manual_seed(1), hint, 1.0)
    # The target is the truth either way.
    for flow in (plain, mixed, always):
        assert torch.equal(flow["r1"], truth_r.repeat_interleave(64, 0))
    # Same seed, same starts and times: every path of `always` ends at the
    # coarse pose (p = 0.02) where `plain`'s ends at the truth (p = 0), so
    # the states differ by t * 0.02.
    assert torch.equal(always["t"], plain["t"])
    assert torch.allclose(always["p_t"] - plain["p_t"], always["t"][:, None] * 0.02 * torch.ones(1, 3), atol=1e-6)
    # About half of `mixed` ends at the coarse pose: its states differ from `plain`'s.
    differ = (mixed["p_t"] - plain["p_t"]).abs().sum(-1) > 1e-7
    assert 0.3 < differ.float().mean().item() < 0.7


def test_an_untrained_refiner_returns_the_pose_it_is_given():
    from poseflow_train.model import Refiner

    cfg = ModelConfig(object_ids=[1], correspondence_points=64, refine_iterations=1)
    g = torch.Generator().manual_seed(2)
    rotation = se3.uniform_rotation((3,), generator=g)
    translation = torch.randn(3, 3, generator=g) * 0.02
    points = torch.randn(3, 64, 3, generator=g) * 0.03
    refiner = Refiner(cfg)
    coordinates, r, p = refiner(points, torch.zeros(3, dtype=torch.long), rotation, translation)
    # The head starts at zero: the coordinates are the points in the object
    # frame of the given pose, and Horn aligns them back to that pose.
    assert torch.allclose(coordinates, (points - translation[:, None]) @ rotation, atol=1e-6)
    assert torch.allclose(r, rotation, atol=1e-4) and torch.allclose(p, translation, atol=1e-6)


def test_perturbed_poses_stay_within_their_bounds():
    from poseflow_train.train import perturbed

    g = torch.Generator().manual_seed(3)
    rotation = se3.uniform_rotation((500,), generator=g)
    translation = torch.zeros(500, 3)
    r, p = perturbed(rotation, translation, 40.0, 2.0, g)
    angles = torch.rad2deg(se3.geodesic_angle(r, rotation))
    assert angles.max().item() <= 40.0 + 1e-3 and angles.mean().item() > 10.0
    assert p.norm(dim=-1).max().item() <= 0.02 + 1e-6


def test_the_learning_rate_decays_by_cosine_over_the_runs_own_time():
    from poseflow_train.train import learning_rate

    config = {"lr": 2e-4, "lr_decay": {"over_s": 1000.0, "final": 1e-5}}
    grown = {"initialised_at_s": 5000.0}
    assert learning_rate({"lr": 2e-4}, {"train_s": 9e9}) == 2e-4
    assert math.isclose(learning_rate(config, dict(grown, train_s=5000.0)), 2e-4)
    assert math.isclose(learning_rate(config, dict(grown, train_s=5500.0)), (2e-4 + 1e-5) / 2)
    assert math.isclose(learning_rate(config, dict(grown, train_s=6000.0)), 1e-5)
    assert math.isclose(learning_rate(config, dict(grown, train_s=7000.0)), 1e-5)
    assert math.isclose(learning_rate(config, {"train_s": 250.0}), 1e-5 + 1.9e-4 * 0.5 * (1 + math.cos(math.pi / 4)))


def test_a_warm_restart_holds_lr_until_its_own_start_then_decays():
    from poseflow_train.train import learning_rate

    config = {"lr": 1e-4, "lr_decay": {"from_s": 8000.0, "over_s": 2000.0, "final": 1e-5}}
    grown = {"initialised_at_s": 5000.0}
    assert math.isclose(learning_rate(config, dict(grown, train_s=6000.0)), 1e-4)
    assert math.isclose(learning_rate(config, dict(grown, train_s=8000.0)), 1e-4)
    assert math.isclose(learning_rate(config, dict(grown, train_s=9000.0)), (1e-4 + 1e-5) / 2)
    assert math.isclose(learning_rate(config, dict(grown, train_s=11000.0)), 1e-5)


class Blind(torch.nn.Module):
    def __init__(self, width):
        super().__init__()
        self.width = width

    def forward(self, values):
        return torch.zeros(values.shape[0], self.width)


def test_the_relative_pose_velocity_net_starts_at_the_coarse_pose_and_sees_poses_relative_to_it():
    from poseflow_train.model import HINT_VALUES, VelocityNet, hint_token

    cfg = ModelConfig(object_ids=[1], width=32, heads=2, dit_depth=1, relative_pose=True, global_condition=False)
    g = torch.Generator().manual_seed(0)
    net = VelocityNet(cfg).eval()
    coarse_r = se3.uniform_rotation((2,), generator=g)
    coarse_p = torch.tensor([[0.01, 0.0, -0.02], [0.0, 0.03, 0.0]])
    tokens = torch.randn(2, 5, cfg.width, generator=g)
    condition = torch.cat([tokens, hint_token(coarse_r, coarse_p, cfg)], 1)
    mask = torch.ones(2, 6)
    samples = 3
    r_t = se3.uniform_rotation((2 * samples,), generator=g)
    p_t = torch.randn(2 * samples, 3, generator=g) * 0.05
    t = torch.full((2 * samples,), 0.4)
    # Zero-initialised heads: every sample's clean pose is its observation's
    # coarse pose.
    with torch.no_grad():
        r1, p1 = net.clean_pose(condition, mask, r_t, p_t, t)
    assert (r1 - coarse_r.repeat_interleave(samples, 0)).abs().max() < 1e-5
    assert (p1 - coarse_p.repeat_interleave(samples, 0)).abs().max() < 1e-7
    # The pose token is built from R_c^T R_t: turning a sample and its
    # coarse pose together (same token values otherwise) changes nothing.
    with torch.no_grad():
        net.rotation_head.weight.normal_(0.0, 0.1, generator=g)
        turn = se3.so3_exp(torch.tensor([0.3, -1.0, 0.7]))
        turned_condition = condition.clone()
        turned_condition[:, -1, :9] = (turn @ coarse_r).reshape(2, 9)
        a, _ = net.clean_pose(condition, mask, r_t, p_t, t)
        # The adaLN conditioning reads the coarse pose's values too: blind it
        # here, so only the pose token could tell the two apart.
        net.hint = Blind(cfg.width)
        a, _ = net.clean_pose(condition, mask, r_t, p_t, t)
        b, _ = net.clean_pose(turned_condition, mask, turn @ r_t, p_t, t)
    # The output turns with the coarse pose: R_c Delta -> Q R_c Delta.
    assert (turn @ a - b).abs().max() < 1e-4
    assert HINT_VALUES == 12


def test_the_diagnostic_reads_a_gain_of_one_for_a_field_that_keeps_the_sample_and_zero_for_one_that_does_not():
    from poseflow_train.diagnose import gains, predicted_turns, turn_about

    g = torch.Generator().manual_seed(3)
    truth = se3.uniform_rotation((6,), generator=g)
    axis = torch.tensor([0.0, 0.0, 1.0])
    # The turn read off is the one applied, whatever the truth.
    assert (predicted_turns(turn_about(truth, axis, 37.0), truth, axis) - 37.0).abs().max() < 1e-3
    thetas, translation = [-60.0, 0.0, 60.0], torch.zeros(6, 3)
    keeps = gains(lambda r, p, t: r, truth, translation, axis, thetas, [0.8])["0.8"]
    assert abs(keeps["gain"] - 1.0) < 1e-3 and abs(keeps["turns"][0] + 60.0) < 1e-2
    pulls = gains(lambda r, p, t: truth, truth, translation, axis, thetas, [0.8])["0.8"]
    assert abs(pulls["gain"]) < 1e-6
    # A field that keeps half of the sample's turn: gain 0.5.
    halfway = gains(lambda r, p, t: turn_about(truth, axis, predicted_turns(r, truth, axis) / 2), truth, translation, axis,
                    thetas, [0.5])
    assert abs(halfway["0.5"]["gain"] - 0.5) < 1e-3


def test_oversampled_objects_are_drawn_by_their_factor_and_bad_factors_are_refused():
    import numpy as np
    import pytest

    from poseflow_train.train import draw, draw_weights

    obj_ids = np.array([1] * 90 + [14] * 10)
    assert draw_weights(obj_ids, {}) is None
    weights = draw_weights(obj_ids, {"14": 9})
    # 10 mug observations at 9x weigh as much as the 90 others together.
    assert abs(weights[obj_ids == 14].sum() - 0.5) < 1e-12
    drawn = draw(np.random.default_rng(0), len(obj_ids), 20000, weights)
    assert abs((obj_ids[drawn] == 14).mean() - 0.5) < 0.02
    uniform = draw(np.random.default_rng(0), len(obj_ids), 20000, None)
    assert abs((obj_ids[uniform] == 14).mean() - 0.1) < 0.02
    for bad in ({"14": 0}, {"14": "x"}, {"mug": 2}, {"5": 2}):
        with pytest.raises(SystemExit):
            draw_weights(obj_ids, bad)


def test_equivalent_targets_are_the_truth_its_symmetric_twins_and_its_hidden_turns():
    from poseflow_train.train import equivalent_targets

    g = torch.Generator().manual_seed(3)
    truth = se3.uniform_rotation((2,), generator=g)
    batch = {"rotation": truth, "translation": torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.02, 0.0]]),
             "object_index": torch.tensor([0, 1])}
    half_turn = se3.so3_exp(torch.tensor([math.pi, 0.0, 0.0]))
    # Object 0: no symmetry (padded); object 1: a two-fold one with an offset.
    table = (torch.stack([torch.stack([torch.eye(3), torch.eye(3)]), torch.stack([torch.eye(3), half_turn])]),
             torch.tensor([[[0.0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 0.03]]]), torch.tensor([1, 2]))
    r, p = equivalent_targets(batch, 400, table, g)
    assert torch.allclose(r[:400], truth[0].expand(400, 3, 3)) and torch.allclose(p[:400], batch["translation"][0].expand(400, 3))
    twin = (se3.geodesic_angle(r[400:], truth[1].expand(400, 3, 3)) > 3.0)
    assert 0.4 < twin.float().mean().item() < 0.6
    assert torch.allclose(p[400:][twin], batch["translation"][1] + truth[1] @ torch.tensor([0.0, 0, 0.03]), atol=1e-6)
    # Hidden turns: object 0 may be turned by 90..120 degrees about its z
    # (bins 9..11 of 36, each 10 degrees wide); object 1's part is in view.
    turns = torch.zeros(2, 36, dtype=torch.bool)
    turns[0, 9:12] = True
    r, p = equivalent_targets(batch, 400, table, g, turns)
    relative = truth[0].T @ r[:400]
    angle = torch.rad2deg(torch.atan2(relative[:, 1, 0], relative[:, 0, 0]))
    assert torch.allclose(relative[:, 2, 2], torch.ones(400), atol=1e-5)  # a turn about z
    assert angle.min().item() >= 85.0 - 1e-3 and angle.max().item() <= 115.0 + 1e-3
    assert angle.max().item() - angle.min().item() > 25.0
    assert torch.allclose(p[:400], batch["translation"][0].expand(400, 3))
    twin = (se3.geodesic_angle(r[400:], truth[1].expand(400, 3, 3)) > 3.0)
    assert 0.4 < twin.float().mean().item() < 0.6


def test_the_energy_score_prefers_samples_spread_like_the_targets_to_samples_on_one_pose():
    from poseflow_train.train import energy_score

    cfg = ModelConfig(object_ids=[1])
    # Targets: half at a +40 degree turn about z, half at -40 (a two-mode view).
    turns = torch.tensor([40.0, -40.0] * 8)
    targets = se3.so3_exp(torch.deg2rad(turns)[:, None] * torch.tensor([0.0, 0.0, 1.0]))[None]
    zeros = torch.zeros(1, 16, 3)

    def score(samples):
        return energy_score(samples, zeros, targets, zeros, cfg, 10.0).item()

    both = targets.clone()
    one_mode = targets[:, :1].expand(1, 16, 3, 3)
    middle = torch.eye(3).expand(1, 16, 3, 3)
    assert score(both) < score(middle) - 0.05
    assert score(both) < score(one_mode) - 0.05
    # Translations count too: a shifted copy of the targets scores worse.
    shifted = energy_score(both, zeros + 0.02, targets, zeros, cfg, 10.0).item()
    assert shifted > score(both) + 0.05


def test_the_rollout_ends_where_a_field_aiming_at_one_pose_sends_every_sample():
    from poseflow_train.evaluate import rollout

    cfg = ModelConfig(object_ids=[1])
    goal_r = se3.so3_exp(torch.tensor([0.3, -0.2, 0.5]))
    goal_p = torch.tensor([0.01, 0.02, 0.5])

    def velocity(condition, mask, r, p, t):
        return se3.target_velocity(r, p, goal_r.expand_as(r), goal_p.expand_as(p), t)

    r, p = rollout(velocity, torch.zeros(2, 4, 8), torch.ones(2, 4), cfg, 6, 5, torch.Generator().manual_seed(0))
    assert r.shape == (2, 6, 3, 3) and p.shape == (2, 6, 3)
    assert (r - goal_r).abs().max().item() < 1e-4
    assert (p - goal_p).abs().max().item() < 1e-5


def test_part_weights_weigh_the_grasps_whose_contact_lies_on_the_part():
    import pytest

    from poseflow_train.grasp import part_weights

    # Grasps approaching along -z (grasp z = object -z), contact 1 cm above
    # the fingertips' origin: at object x = 0.02 and 0.07.
    down = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    rotation = down.expand(2, 3, 3)
    translation = torch.tensor([[0.02, 0.0, 0.0], [0.07, 0.0, 0.0]])
    part = {"axis": [1.0, 0.0, 0.0], "beyond": 0.05, "factor": 10.0}
    assert part_weights(rotation, translation, 0.01, part).tolist() == [1.0, 10.0]
    assert part_weights(rotation, translation, 0.01, None).tolist() == [1.0, 1.0]
    # The contact point, not the fingertips' origin: approaching along
    # object -x with the origin at x = 0.045, the contact is at x = 0.055.
    along_minus_x = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    assert part_weights(along_minus_x[None], torch.tensor([[0.045, 0.0, 0.0]]), 0.01, part).tolist() == [10.0]
    with pytest.raises(SystemExit, match="oversample_parts"):
        part_weights(rotation, translation, 0.01, {"axis": [0.0, 0.0, 0.0], "beyond": 0.05, "factor": 2.0})
    with pytest.raises(SystemExit, match="oversample_parts"):
        part_weights(rotation, translation, 0.01, {"beyond": 0.05})


def test_the_weight_average_follows_its_closed_form_and_is_swapped_in_and_out():
    from poseflow_train.train import WeightAverage

    module = torch.nn.Linear(2, 1)
    with torch.no_grad():
        module.weight.fill_(1.0)
        module.bias.fill_(0.0)
    modules = {"m": module}
    average = WeightAverage(modules, 0.9)
    for value in (2.0, 4.0):
        with torch.no_grad():
            module.weight.fill_(value)
        average.update(modules)
    # 0.9 (0.9 * 1 + 0.1 * 2) + 0.1 * 4 = 1.39
    assert torch.allclose(average.shadow["m"]["weight"], torch.full((1, 2), 1.39))
    with average.applied(modules):
        assert torch.allclose(module.weight, torch.full((1, 2), 1.39))
    assert torch.equal(module.weight, torch.full((1, 2), 4.0))
    with pytest.raises(SystemExit, match="ema 1.0"):
        WeightAverage(modules, 1.0)


def test_a_checkpoint_keeps_the_average_and_the_portable_weights_are_it(tmp_path):
    import numpy as np

    from poseflow_train.train import WeightAverage, model_weights, save_checkpoint

    cfg = ModelConfig(object_ids=[1])
    module = torch.nn.Linear(2, 1)
    modules = {"encoder": module, "velocity": torch.nn.Linear(1, 1)}
    average = WeightAverage(modules, 0.5)
    with torch.no_grad():
        module.weight.fill_(3.0)
    average.update(modules)
    optimiser = torch.optim.AdamW(module.parameters())
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, modules, optimiser, {"step": 1, "train_s": 1.0}, torch.Generator(),
                    np.random.default_rng(0), cfg, average)
    full = torch.load(path, weights_only=False)
    portable = torch.load(tmp_path / "weights.pt", weights_only=False)
    assert torch.equal(full["encoder"]["weight"], torch.full((1, 2), 3.0))
    assert torch.equal(model_weights(full)["encoder"]["weight"], average.shadow["encoder"]["weight"])
    assert portable["averaged"] and torch.equal(portable["encoder"]["weight"].float(),
                                                average.shadow["encoder"]["weight"].half().float())
    # A run resumed from its checkpoint takes the average up where it was.
    again = WeightAverage(modules, 0.5, full["ema"])
    assert torch.equal(again.shadow["encoder"]["weight"], average.shadow["encoder"]["weight"])
    # Without an average, the model is the weights.
    assert model_weights({"encoder": 1, "velocity": 2}) == {"encoder": 1, "velocity": 2}
