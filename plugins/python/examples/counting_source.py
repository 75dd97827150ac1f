#!/usr/bin/env python3
"""A source stage in Python: the smoke graph's counting source.

Frame f carries `samples` poses whose value i is (7919 f + 104729 i) mod
1000003, exactly as the Rust `smoke-source` sends them, so the Rust
checking sink verifies every value. Parameters (graph `params`): `frames`
(default 1000), `samples` (default 4), `rate_hz` (pacing, optional)."""

import poseflow_stage


def counting_source(frames, samples):
    frame = 0

    def produce():
        nonlocal frame
        if frame >= frames:
            return None
        header = poseflow_stage.HypothesesHeader()
        header.header.frame_id, header.header.object_id = frame, 1
        header.sample_count, header.step_count = samples, 1
        values = [float((frame * 7919 + i * 104729) % 1000003) for i in range(poseflow_stage.POSE_LEN * samples)]
        frame += 1
        return header, values

    return produce


if __name__ == "__main__":
    params = poseflow_stage.wiring().get("params") or {}
    produce = counting_source(int(params.get("frames", 1000)), int(params.get("samples", 4)))
    poseflow_stage.run_source(produce, poseflow_stage.HypothesesHeader)
