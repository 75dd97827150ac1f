#!/usr/bin/env python3
"""A plug-in stage in Python: negates every value of Hypotheses messages.

Drop-in replacement for the Rust `testbed-relay` of tests/graphs/relay.toml
(see tests/e2e/plugins.rs, `a_python_stage_replaces_a_rust_one`)."""

import poseflow_stage


def negate(header, floats):
    out = poseflow_stage.HypothesesHeader()
    out.header = header.header
    out.sample_count, out.step_count = header.sample_count, header.step_count
    return out, [-v for v in floats]


if __name__ == "__main__":
    poseflow_stage.run_transform(negate)
