"""The detector network learns pixels' objects (a synthetic pattern it
must fail on untrained), and its input matches the stage's layout."""

import numpy as np
import torch
import torch.nn.functional as F

import pytest

from poseflow_train.detector import (
    HEIGHT,
    WIDTH,
    build,
    class_weights,
    evaluate_arrays,
    input_size,
    random_crops,
    to_input,
)


def squares(n, rng, height=HEIGHT, width=WIDTH, side=30):
    """Images with one square per image whose colour says its class, on a
    table at 1 m; the square stands 10 cm nearer."""
    rgb = np.full((n, height, width, 3), 90, np.uint8)
    depth = np.full((n, height, width), 1000, np.uint16)
    labels = np.zeros((n, height, width), np.uint8)
    colours = {1: (220, 40, 40), 2: (40, 220, 40)}
    for i in range(n):
        k = 1 + i % 2
        y, x = rng.integers(10, height - side - 10), rng.integers(10, width - side - 10)
        rgb[i, y : y + side, x : x + side] = colours[k]
        depth[i, y : y + side, x : x + side] = 900
        labels[i, y : y + side, x : x + side] = k
    return rgb, depth, labels


def test_input_layout():
    x = to_input(np.full((1, HEIGHT, WIDTH, 3), 255, np.uint8), np.full((1, HEIGHT, WIDTH), 1500, np.uint16))
    assert x.shape == (1, 5, HEIGHT, WIDTH)
    assert torch.allclose(x[0, :3], torch.ones(3, HEIGHT, WIDTH))
    assert torch.allclose(x[0, 3], torch.full((HEIGHT, WIDTH), 0.75))
    assert torch.all(x[0, 4] == 1)


@pytest.mark.parametrize("arch", ["unet", "fine"])
def test_a_trained_detector_finds_the_objects_an_untrained_one_misses(arch):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    # Half the input of either architecture keeps the test quick; both are
    # convolutional, so the size is theirs to take.
    height, width, _ = input_size(arch)
    rgb, depth, labels = squares(16, rng, height // 2, width // 2, side=height // 8)
    model = build(arch, 3, width=8)
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


@pytest.mark.parametrize("arch", ["unet", "fine"])
def test_the_output_has_the_input_size(arch):
    height, width, down = input_size(arch)
    assert (height * down, width * down) == (480, 640)
    model = build(arch, 4, width=8).eval()
    with torch.no_grad():
        assert model(torch.zeros(1, 5, height, width)).shape == (1, 4, height, width)


def test_random_crops_cut_the_same_window_from_image_depth_and_labels():
    rng = np.random.default_rng(1)
    n, h, w = 3, 12, 20
    rgb = np.arange(n * h * w * 3, dtype=np.int64).reshape(n, h, w, 3) % 251
    depth = (np.arange(n * h * w).reshape(n, h, w) % 4093).astype(np.uint16)
    labels = (np.arange(n * h * w).reshape(n, h, w) % 7).astype(np.uint8)
    c_rgb, c_depth, c_labels = random_crops(rgb.astype(np.uint8), depth, labels, (5, 8), rng)
    assert c_rgb.shape == (n, 5, 8, 3) and c_depth.shape == (n, 5, 8) and c_labels.shape == (n, 5, 8)
    for i in range(n):
        # Each pixel of a crop is unique in its image's depth: find the window.
        y, x = np.argwhere(depth[i] == c_depth[i, 0, 0])[0]
        assert np.array_equal(c_rgb[i], rgb[i, y : y + 5, x : x + 8].astype(np.uint8))
        assert np.array_equal(c_labels[i], labels[i, y : y + 5, x : x + 8])
    # A window larger than the image is the whole image.
    whole = random_crops(rgb.astype(np.uint8), depth, labels, (50, 50), rng)
    assert whole[1].shape == depth.shape


def test_the_exported_probabilities_are_the_softmax_of_the_logits():
    from poseflow_train.detector import Exported

    torch.manual_seed(3)
    model = build("unet", 4, width=8).eval()
    x = torch.rand(2, 5, 24, 32)
    with torch.no_grad():
        assert torch.allclose(Exported(model)(x), torch.softmax(model(x), dim=1), atol=1e-6)


def test_a_run_resumes_from_its_portable_weights_on_another_machine(tmp_path):
    from poseflow_train.detector import PORTABLE, load_state, save

    torch.manual_seed(4)
    model = build("fine", 3, width=8)
    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-3)
    save(model, optimiser, 7, 12.5, tmp_path / "detector.pt")
    full = load_state(tmp_path)
    assert "optimiser" in full and full["step"] == 7
    (tmp_path / "detector.pt").unlink()
    portable = load_state(tmp_path)
    assert (tmp_path / PORTABLE).exists() and "optimiser" not in portable
    assert (portable["step"], portable["elapsed_s"]) == (7, 12.5)
    for name, value in model.state_dict().items():
        restored = portable["model"][name]
        assert restored.dtype == value.dtype, name
        # Half precision: within its rounding of the single-precision weights.
        assert torch.allclose(restored, value, rtol=1e-3, atol=1e-4), name
