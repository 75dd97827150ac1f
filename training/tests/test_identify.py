"""The identifier's pieces: connected regions, the crop the stage builds
(services/detector/src/identify.rs), and a network that learns to name
regions (must fail untrained)."""

import numpy as np
import torch
import torch.nn.functional as F

from poseflow_train.identify import CHANNELS, CROP, Identifier, components, crop_input, grown


def test_components_are_same_label_4_connected_regions():
    labels = np.array([[[1, 1, 0, 2], [0, 1, 0, 2], [3, 1, 1, 0], [3, 0, 1, 1]], [[2, 0, 2, 2], [2, 2, 0, 0], [0, 0, 0, 0], [1, 0, 0, 1]]], np.uint8)
    ids = components(labels)
    # Image 0: the 1s form one region (first cell 0), the 2s one, the 3s one.
    assert set(ids[0][labels[0] == 1]) == {0}
    assert set(ids[0][labels[0] == 2]) == {3}
    assert set(ids[0][labels[0] == 3]) == {8}
    assert (ids[labels == 0] == -1).all()
    # Image 1: the 2s at (0, 0) and (0, 2) only touch diagonally or through
    # (1, 1): (0,0)-(1,0)-(1,1) is one region, (0,2)-(0,3) another; the two
    # 1s are apart.
    second = ids[1]
    assert second[0, 0] == second[1, 0] == second[1, 1] != second[0, 2] == second[0, 3]
    assert second[3, 0] != second[3, 3]


def test_grown_and_eroded_are_square_neighbourhoods():
    region = np.zeros((5, 5), bool)
    region[2, 2] = True
    assert grown(region, 1).sum() == 9
    assert grown(grown(region, 1), -1).sum() == 1


def test_crop_layout_matches_the_stage():
    # The same 4 × 4 grid as the stage's closed-form test: cell (x, y) red
    # 2x + 1, green 2y + 1, depth 1 m + (2x + 2y + 2) cm.
    rgb = np.zeros((4, 4, 3), np.uint8)
    depth = np.zeros((4, 4), np.uint16)
    for y in range(4):
        for x in range(4):
            rgb[y, x] = (2 * x + 1, 2 * y + 1, 9)
            depth[y, x] = 1000 + 10 * (2 * x + 2 * y + 2)
    region = np.zeros((4, 4), bool)
    region[1:3, 1:3] = True
    import poseflow_train.identify as identify

    saved = identify.CROP, identify.CONTEXT
    identify.CROP, identify.CONTEXT = 4, 1.0
    try:
        x = crop_input(rgb, depth, region, fx=400.0)
    finally:
        identify.CROP, identify.CONTEXT = saved
    assert x.shape == (CHANNELS, 4, 4)
    assert np.allclose(x[0] * 255, rgb[..., 0]) and np.allclose(x[1] * 255, rgb[..., 1])
    assert np.array_equal(x[5], region.astype(np.float32))
    # Median of 1.06, 1.08, 1.08, 1.10 m (the lower middle): 1.08.
    assert np.allclose(x[3], np.clip((depth / 1000.0 - 1.08) / 0.15, -1, 1), atol=1e-6)
    assert np.allclose(x[6], 4 * 2 * 1.08 / 400.0 / 0.3)


def squares(n, rng):
    """Crops of one square region whose colour names its class (1 or 2)."""
    xs, ys = [], []
    for i in range(n):
        k = 1 + i % 2
        rgb = np.full((40, 40, 3), 90, np.uint8)
        depth = np.full((40, 40), 1000, np.uint16)
        region = np.zeros((40, 40), bool)
        y, x = rng.integers(5, 25, size=2)
        region[y : y + 10, x : x + 10] = True
        rgb[region] = (220, 40, 40) if k == 1 else (40, 220, 40)
        depth[region] = 900
        xs.append(crop_input(rgb, depth, region, 572.0))
        ys.append(k)
    return torch.as_tensor(np.stack(xs)), torch.as_tensor(ys)


def test_a_trained_identifier_names_regions_an_untrained_one_does_not():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    x, y = squares(32, rng)
    model = Identifier(3, width=8)
    model.eval()
    with torch.no_grad():
        untrained = (model(x).argmax(1) == y).float().mean().item()
    optimiser = torch.optim.AdamW(model.parameters(), lr=5e-3)
    model.train()
    for _ in range(40):
        loss = F.cross_entropy(model(x), y)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    model.eval()
    test_x, test_y = squares(16, np.random.default_rng(1))
    with torch.no_grad():
        trained = (model(test_x).argmax(1) == test_y).float().mean().item()
    assert trained == 1.0, trained
    assert untrained <= 0.6, untrained
    assert x.shape[-1] == CROP
