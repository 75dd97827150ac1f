#!/usr/bin/env python3
"""A sink stage in Python: reads the Estimates of a pose graph as a robot
program would, and prints one line per object: the selected pose, how
sure the estimate is, and the distinct poses it could be (modes: their
share of the samples and how far each is turned from the selected pose).

Parameters (graph `params`): `format` = "text" (default) or "json" (one
JSON object per line: `poseflow_stage.estimate_dict`); `output` = a file
to append the lines to instead of stdout."""

import json
import math
import sys

import poseflow_stage


def angle_deg(a, b):
    """The rotation angle between two rotation matrices (lists of rows), degrees."""
    trace = sum(a[r][c] * b[r][c] for r in range(3) for c in range(3))
    return math.degrees(math.acos(max(-1.0, min(1.0, (trace - 1) / 2))))


def describe(estimate):
    """One human-readable line: translation in mm, the rotation spread, and
    each mode's share of the samples and its rotation away from the best
    pose (two modes far apart: the view is ambiguous)."""
    best = estimate["best"]
    t_mm = ", ".join(f"{1000 * v:.1f}" for v in best["t"])
    spread_deg = math.degrees(math.sqrt(max(estimate["rotation_trace_rad2"], 0.0) / 3))
    modes = ", ".join(
        f"{100 * mode['weight']:.0f} % at {angle_deg(best['R'], mode['R']):.0f}°" for mode in estimate["modes"]
    )
    return (
        f"frame {estimate['frame']} object {estimate['object']}: t = ({t_mm}) mm, "
        f"rotation spread {spread_deg:.1f}°, modes: {modes or 'none'}"
    )


def printer(fmt, out):
    def consume(header, floats):
        estimate = poseflow_stage.estimate_dict(header, floats)
        line = json.dumps(estimate) if fmt == "json" else describe(estimate)
        print(line, file=out, flush=True)

    return consume


if __name__ == "__main__":
    params = poseflow_stage.wiring().get("params") or {}
    fmt = params.get("format", "text")
    if fmt not in ("text", "json"):
        raise SystemExit(f"param `format`: expected \"text\" or \"json\", found {fmt!r}")
    out = open(params["output"], "a", encoding="utf-8") if "output" in params else sys.stdout
    poseflow_stage.run_sink(printer(fmt, out), poseflow_stage.EstimateHeader)
