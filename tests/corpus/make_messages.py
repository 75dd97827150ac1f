#!/usr/bin/env python3
"""Builds tests/corpus/messages: contract messages as a stage receives them,
some consistent, most not. Standard library only.

    python3 tests/corpus/make_messages.py tests/corpus/messages

File layout (also the input of the `message` fuzz target, fuzz/): one byte
choosing the type (its index in poseflow_graph::PUBLISH_SUBSCRIBE_MESSAGES:
3 = Hypotheses, 4 = Estimate), the header's bytes (#[repr(C)], little
endian; see shared/contracts), then the payload as little-endian f32.
"""
import struct
import sys
from pathlib import Path

HYPOTHESES, ESTIMATE = 3, 4
IDENTITY = [1, 0, 0, 0, 1, 0, 0, 0, 1, 0.1, 0.0, 0.5]


def base(frame_id=7, object_id=1, flags=0):
    """Header: frame_id u64, object_id u32, flags u32, 8 stage stamps u64 (80 bytes)."""
    return struct.pack("<QII8Q", frame_id, object_id, flags, *([0] * 8))


def category(code=0, size=(0.0, 0.0, 0.0)):
    """ObjectCategory: code u32, size 3 f32 (16 bytes)."""
    return struct.pack("<I3f", code, *size)


def hypotheses(sample_count, values, kind=None):
    kind = kind or category()
    return bytes([HYPOTHESES]) + base() + struct.pack("<II", sample_count, 5) + kind + floats(values)


def estimate(mode_count, hypothesis_count, kept_count, values, selection=3, kind=None):
    header = (base() + floats(IDENTITY) + floats(IDENTITY) + floats([0.0] * 36) + floats([0.0])
              + struct.pack("<IIIII", selection, mode_count, hypothesis_count, kept_count, 1)
              + (kind or category()))
    assert len(header) == 360
    return bytes([ESTIMATE]) + header + floats(values)


def floats(values):
    return struct.pack(f"<{len(values)}f", *values)


def main(target):
    target = Path(target)
    target.mkdir(parents=True, exist_ok=True)
    weighted = IDENTITY + [0.0]
    cases = {
        "hypotheses.bin": hypotheses(2, IDENTITY * 2),
        "hypotheses-short-payload.bin": hypotheses(2, IDENTITY + IDENTITY[:8]),
        "hypotheses-zero-samples.bin": hypotheses(0, []),
        "hypotheses-too-many-samples.bin": hypotheses(5000, []),
        "hypotheses-truncated-header.bin": (bytes([HYPOTHESES]) + base())[:60],
        "estimate.bin": estimate(0, 2, 1, weighted * 2),
        "estimate-kept-more-than-scored.bin": estimate(0, 2, 3, weighted * 2),
        "estimate-mode-count-huge.bin": estimate(0xFFFFFFFF, 2, 1, weighted * 2),
        "estimate-unknown-selection.bin": estimate(0, 2, 1, weighted * 2, selection=9),
        "estimate-long-payload.bin": estimate(0, 2, 1, weighted * 3),
        "estimate-mug.bin": estimate(0, 2, 1, weighted * 2, kind=category(6, (0.12, 0.1, 0.09))),
        "estimate-mug-nan-size.bin": estimate(0, 2, 1, weighted * 2, kind=category(6, (float("nan"), 0.1, 0.09))),
        "hypotheses-can-zero-size.bin": hypotheses(2, IDENTITY * 2, kind=category(4, (0.08, 0.0, 0.08))),
    }
    for name, data in cases.items():
        (target / name).write_bytes(data)


if __name__ == "__main__":
    main(*sys.argv[1:])
