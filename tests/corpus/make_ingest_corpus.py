#!/usr/bin/env python3
"""Builds tests/corpus/ingest: a small BOP dataset whose images each carry
one kind of bad input for the ingest stage. Standard library only.

    poseflow render --models objects/lmo --out /tmp/corpus --scenes 1 \
        --frames-per-scene 8 --seed 4 --occlusion low --width 160 --height 120 --split test --clean
    python3 tests/corpus/make_ingest_corpus.py /tmp/corpus tests/corpus/ingest

Scene 0: image 0 good; 1 RGB missing; 2 RGB truncated; 3 depth 8-bit;
4 depth 80x60; 5 masks: instance 0 empty, 1 three pixels, 2 missing;
6 depth all zero; 7 cam_K missing. Scene 1: a scene_camera.json with NaN
intrinsics (as Python's json module writes them), so not JSON at all;
its images are never reached.
"""
import json
import shutil
import struct
import sys
import zlib
from pathlib import Path


def png(path, width, height, bit_depth, rows):
    """Writes a greyscale PNG (colour type 0) of `rows` (bytes per row)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    raw = b"".join(b"\x00" + row for row in rows)
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def main(source, target):
    source, target = Path(source), Path(target)
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source / "test", target / "test")
    shutil.copy(source / "camera.json", target / "camera.json")
    scene = target / "test" / "000000"
    (scene / "rgb" / "000001.png").unlink()
    truncated = (scene / "rgb" / "000002.png").read_bytes()[:100]
    (scene / "rgb" / "000002.png").write_bytes(truncated)
    png(scene / "depth" / "000003.png", 160, 120, 8, [bytes([100] * 160)] * 120)
    png(scene / "depth" / "000004.png", 80, 60, 16, [struct.pack(">80H", *([8000] * 80))] * 60)
    png(scene / "mask_visib" / "000005_000000.png", 160, 120, 8, [bytes(160)] * 120)
    tiny = [bytes(160)] * 120
    tiny[60] = bytes(80) + b"\xff\xff\xff" + bytes(77)
    png(scene / "mask_visib" / "000005_000001.png", 160, 120, 8, tiny)
    (scene / "mask_visib" / "000005_000002.png").unlink()
    png(scene / "depth" / "000006.png", 160, 120, 16, [bytes(320)] * 120)
    cameras = json.loads((scene / "scene_camera.json").read_text())
    del cameras["7"]["cam_K"]
    (scene / "scene_camera.json").write_text(json.dumps(cameras, indent=1))

    broken = target / "test" / "000001"
    broken.mkdir()
    for name in ("scene_gt.json", "scene_gt_info.json"):
        shutil.copy(scene / name, broken / name)
    cameras["0"]["cam_K"][0] = float("nan")
    (broken / "scene_camera.json").write_text(json.dumps(cameras, indent=1))

    targets = [{"im_id": im, "inst_count": 1, "obj_id": obj, "scene_id": s}
               for s, images in ((0, range(8)), (1, range(1))) for im in images for obj in (1, 10, 11)]
    (target / "test_targets_bop19.json").write_text(json.dumps(targets, indent=1))
    shutil.rmtree(scene / "mask")  # ingest reads visible masks only


if __name__ == "__main__":
    main(*sys.argv[1:])
