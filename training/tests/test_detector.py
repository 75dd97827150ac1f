"""The detector network learns pixels' objects (a synthetic pattern it
must fail on untrained), and its input matches the stage's layout."""

import numpy as np
import torch
import torch.nn.functional as F

from poseflow_train.detector import HEIGHT, WIDTH, Detector, class_weights, evaluate_arrays, to_input


def squares(n, rng):
    """Images with one square per image whose colour says its class, on a
    table at 1 m; the square stands 10 cm nearer."""
    rgb = np.full((n, HEIGHT, WIDTH, 3), 90, np.uint8)
    depth = np.full((n, HEIGHT, WIDTH), 1000, np.uint16)
    labels = np.zeros((n, HEIGHT, WIDTH), np.uint8)
    colours = {1: (220, 40, 40), 2: (40, 220, 40)}
    for i in range(n):
        k = 1 + i % 2
        y, x = rng.integers(10, HEIGHT - 40), rng.integers(10, WIDTH - 40)
        rgb[i, y : y + 30, x : x + 30] = colours[k]
        depth[i, y : y + 30, x : x + 30] = 900
        labels[i, y : y + 30, x : x + 30] = k
    return rgb, depth, labels


def test_input_layout():
    x = to_input(np.full((1, HEIGHT, WIDTH, 3), 255, np.uint8), np.full((1, HEIGHT, WIDTH), 1500, np.uint16))
    assert x.shape == (1, 5, HEIGHT, WIDTH)
    assert torch.allclose(x[0, :3], torch.ones(3, HEIGHT, WIDTH))
    assert torch.allclose(x[0, 3], torch.full((HEIGHT, WIDTH), 0.75))
    assert torch.all(x[0, 4] == 1)


def test_a_trained_detector_finds_the_objects_an_untrained_one_misses():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rgb, depth, labels = squares(16, rng)
    model = Detector(3, width=8)
    untrained = evaluate_arrays(model, rgb, depth, labels, [1, 2])["mean_iou"]
    optimiser = torch.optim.AdamW(model.parameters(), lr=5e-3)
    weights = torch.tensor(class_weights(2))
    for _ in range(60):
        model.train()
        # The training loss's class weights, which the evaluation divides out.
        loss = F.cross_entropy(model(to_input(rgb, depth)), torch.as_tensor(labels, dtype=torch.long), weight=weights)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    trained = evaluate_arrays(model, rgb, depth, labels, [1, 2])["mean_iou"]
    assert untrained < 0.3 and trained > 0.7, (untrained, trained)


def test_learning_rate_decays_by_a_cosine_to_five_percent():
    from poseflow_train.detector import learning_rate

    assert learning_rate(1.0, 123, 0) == 1.0
    assert learning_rate(1.0, 0, 100) == 1.0
    assert abs(learning_rate(1.0, 50, 100) - (0.05 + 0.95 * 0.5)) < 1e-12
    assert abs(learning_rate(1.0, 100, 100) - 0.05) < 1e-12
    assert abs(learning_rate(1.0, 1000, 100) - 0.05) < 1e-12
