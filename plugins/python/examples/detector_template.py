#!/usr/bin/env python3
"""A detector stage in Python: Frame in, Frame out with its own detections.

This is the place to plug in Mask R-CNN, CNOS, SAM or any segmenter: put
the model call in `detect()`, which gets the RGB (H×W×3, 0-255) and depth
(H×W, metres) and returns detections as (obj_id, score, x, y, width,
height, mask) with `mask` the box's row-major 0/1 values. As shipped it
stands in for a detector by keeping the incoming detections whose score
and mask area reach `min_score` and `min_area` (graph params), so graphs
and tests can run it without a model.

Wire it between the frame source and ingest:

    [stages.detector]
    exe = "target/python-venv/bin/python"
    args = ["plugins/python/examples/detector_template.py"]
    inputs = ["frames"]
    outputs = ["detected"]
    params = { min_area = 150 }
"""

import poseflow_stage
from poseflow_stage import DETECTION_LEN, FrameHeader

PARAMS = poseflow_stage.wiring().get("params", {})
MIN_AREA = float(PARAMS.get("min_area", 0))
MIN_SCORE = float(PARAMS.get("min_score", 0.0))


def incoming_detections(header, floats):
    """The detections already in the frame, as detect() returns them."""
    pixels = header.intrinsics.width * header.intrinsics.height
    records = floats[4 * pixels : 4 * pixels + DETECTION_LEN * header.detection_count]
    masks_start = 4 * pixels + DETECTION_LEN * header.detection_count
    detections = []
    for k in range(header.detection_count):
        obj_id, _instance, score, x, y, w, h, offset = records[k * DETECTION_LEN : (k + 1) * DETECTION_LEN]
        start = masks_start + int(offset)
        detections.append((int(obj_id), score, int(x), int(y), int(w), int(h), floats[start : start + int(w * h)]))
    return detections


def detect(header, floats):
    """Replace with a model call. Here: filter the incoming detections."""
    return [d for d in incoming_detections(header, floats) if d[1] >= MIN_SCORE and sum(d[6]) >= MIN_AREA]


def republish(header, floats):
    detections = detect(header, floats)
    out = FrameHeader()
    out.header, out.intrinsics = header.header, header.intrinsics
    out.scene_id, out.image_id = header.scene_id, header.image_id
    out.detection_count = len(detections)
    out.mask_len = sum(len(d[6]) for d in detections)
    pixels = header.intrinsics.width * header.intrinsics.height
    values = floats[: 4 * pixels]
    offset = 0
    for instance, (obj_id, score, x, y, w, h, mask) in enumerate(detections):
        values += [obj_id, instance, score, x, y, w, h, offset]
        offset += len(mask)
    for detection in detections:
        values += list(detection[6])
    return out, values


if __name__ == "__main__":
    poseflow_stage.run_transform(republish, header_type=FrameHeader, slot=None)
