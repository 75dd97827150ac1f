#!/usr/bin/env python3
"""A plug-in relay that breaks the message contract on purpose: every
EVERY-th frame (argv[1], default 50) goes out with a header announcing one
more sample than its payload holds; the others are negated as by
plugins/python/examples/negating_relay.py. The Rust sink must reject exactly those
(counted as errors, logged with the message type and both lengths) and
keep going. Used by tests/e2e/plugins.rs."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins" / "python" / "examples"))

import poseflow_stage  # noqa: E402
from negating_relay import negate  # noqa: E402

EVERY = int(sys.argv[1]) if len(sys.argv) > 1 else 50


def garble(header, floats):
    out, values = negate(header, floats)
    if header.header.frame_id % EVERY == EVERY - 1:
        out.sample_count += 1
    return out, values


if __name__ == "__main__":
    poseflow_stage.run_transform(garble)
