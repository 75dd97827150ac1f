"""Hidden-part arcs on a constructed view with a closed-form answer."""

import numpy as np

from poseflow_train.arcs import BINS, hidden_turns


def test_a_part_is_hidden_exactly_where_an_occluder_stands_in_front_of_it():
    # 640 x 480 depth: an occluder at 0.5 m over the left half, a wall at
    # 1 m on the right. The object sits at 0.8 m with its z axis pointing
    # up in the image (camera -y) and its x axis to the left (camera -x),
    # so a part at object (0.1, 0, 0) turned by phi about object z is at
    # camera x = -0.1 cos(phi), z = 0.8 - 0.1 sin(phi): behind the
    # occluder (hidden) for cos(phi) > 0, in front of the wall otherwise.
    depth = np.full((480, 640), 1.0)
    depth[:, :320] = 0.5
    rotation = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])
    translation = np.array([0.0, 0.0, 0.8])
    part = np.array([[0.1, 0.0, 0.0]])
    intrinsics = (600.0, 600.0, 320.5, 240.5)
    turns = hidden_turns(part, rotation, translation, depth, intrinsics, (0, 0, 1), hidden_pixels=0)
    degrees = np.arange(BINS) * 360 / BINS
    for k, phi in enumerate(degrees):
        if abs(np.cos(np.radians(phi))) > 0.05:
            assert turns[k] == (np.cos(np.radians(phi)) > 0), (phi, turns[k])
    # The same part in view at the pose itself: no arc at all.
    seen = hidden_turns(part, rotation @ np.diag([-1.0, -1.0, 1.0]), translation, depth, intrinsics, (0, 0, 1), 0)
    assert not seen.any()
    # Where the camera measured nothing, nothing is seen.
    assert hidden_turns(part, rotation, translation, np.zeros_like(depth), intrinsics, (0, 0, 1), 0).all()
