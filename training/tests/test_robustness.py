import numpy as np

from poseflow_train.robustness import dilate, depth_hole, depth_shift, mask_grown


def square(side, first, last):
    mask = np.zeros((side, side), dtype=bool)
    mask[first:last + 1, first:last + 1] = True
    return mask


def test_masks_grow_and_shrink_by_whole_pixels():
    mask = square(12, 4, 7)
    assert (dilate(mask, 2) == square(12, 2, 9)).all()
    assert (mask_grown(1)["mask"](mask, None, None) == square(12, 3, 8)).all()
    assert (mask_grown(-1)["mask"](mask, None, None) == square(12, 5, 6)).all()


def test_a_depth_hole_takes_the_share_of_the_mask_and_nothing_outside():
    mask = square(20, 5, 14)
    depth = np.full((20, 20), 1000.0)
    holed = depth_hole(0.2)["depth_per_mask"](mask, depth, np.random.default_rng(0))
    assert (holed == 0).sum() == 20
    assert (holed[~mask] == 1000.0).all()


def test_a_depth_shift_moves_right_and_leaves_no_measurement_behind():
    depth = np.arange(12, dtype=np.float64).reshape(3, 4) + 1
    moved = depth_shift(2)["depth"](depth, 0.1, None)
    assert (moved[:, :2] == 0).all() and (moved[:, 2:] == depth[:, :2]).all()
