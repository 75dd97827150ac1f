"""Classical baseline: register each object model to its observed partial
cloud with FPFH features + RANSAC, refined by point-to-plane ICP (Open3D),
and write the poses as a BOP19 results file that `poseflow eval --results`
scores on the same instances as the graph.

    target/evaluation-venv/bin/python evaluation/baseline/fpfh_ransac_icp.py \\
        --dataset training/data/lmo10 --out target/eval-baseline/baseline_lmo10-test.csv

Observed cloud: the pixels of the instance's visible mask (ground-truth
masks, as the graph's frame source uses) with a depth, back-projected with
cam_K (metres, camera frame). Model cloud: 5000 points sampled on the mesh
(BOP models are in millimetres). Both are voxel-downsampled at 1/25 of the
object's diameter; FPFH radius 5 voxels; RANSAC with 3-point samples,
edge-length and distance checks; ICP point-to-plane within 1.5 voxels.
Time per image = the sum of its instances' registration times (one thread
of Open3D work per instance; the machine's cores are left to OpenMP).
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from PIL import Image

MODEL_POINTS = 5000
VOXELS_PER_DIAMETER = 25.0


def read_json(path):
    return json.loads(Path(path).read_text())


def targets(dataset, split, targets_file):
    """[(scene_id, im_id, [obj_id])] in file order, or every image of the
    split with all its annotated objects."""
    file = Path(targets_file) if targets_file else Path(dataset) / "test_targets_bop19.json"
    out = {}
    if file.is_file():
        for entry in read_json(file):
            out.setdefault((entry["scene_id"], entry["im_id"]), []).append(entry["obj_id"])
        return [(s, i, objs) for (s, i), objs in out.items()]
    images = []
    for scene in sorted(p for p in (Path(dataset) / split).iterdir() if p.is_dir()):
        for im_id in sorted(int(k) for k in read_json(scene / "scene_camera.json")):
            images.append((int(scene.name), im_id, []))
    return images


def model_cloud(models_dir, obj_id):
    """MODEL_POINTS points on the mesh, metres, object frame."""
    path = Path(models_dir) / f"obj_{obj_id:06d}.ply"
    mesh = o3d.io.read_triangle_mesh(str(path))
    if not mesh.has_triangles():
        raise SystemExit(f"{path}: no triangles (expected a BOP model mesh)")
    mesh.scale(0.001, center=np.zeros(3))
    return mesh.sample_points_uniformly(number_of_points=MODEL_POINTS)


def observed_cloud(depth_mm, mask, cam_k):
    v, u = np.nonzero(mask & (depth_mm > 0))
    z = depth_mm[v, u] / 1000.0
    fx, cx, fy, cy = cam_k[0], cam_k[2], cam_k[4], cam_k[5]
    points = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points)
    return cloud


def features(cloud, voxel):
    down = cloud.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, fpfh


def register(model, observed, voxel):
    """camera_from_object (4x4) and the ICP fitness."""
    source, source_fpfh = features(model, voxel)
    target, target_fpfh = features(observed, voxel)
    reg = o3d.pipelines.registration
    ransac = reg.registration_ransac_based_on_feature_matching(
        source, target, source_fpfh, target_fpfh, False, 1.5 * voxel,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    icp = reg.registration_icp(source, target, 1.5 * voxel, ransac.transformation,
                               reg.TransformationEstimationPointToPlane())
    return icp.transformation, icp.fitness


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--targets")
    parser.add_argument("--models", help="BOP models directory [default: <dataset>/models]")
    parser.add_argument("--out", required=True, help="BOP19 results file to write")
    parser.add_argument("--min-points", type=int, default=30, help="fewer observed points: no estimate")
    args = parser.parse_args()
    o3d.utility.random.seed(0)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    models_dir = Path(args.models or Path(args.dataset) / "models")
    info = read_json(models_dir / "models_info.json")
    models = {}
    rows = []
    images = targets(args.dataset, args.split, args.targets)
    started = time.monotonic()
    for n, (scene_id, im_id, wanted) in enumerate(images):
        scene = Path(args.dataset) / args.split / f"{scene_id:06d}"
        camera = read_json(scene / "scene_camera.json")[str(im_id)]
        gts = read_json(scene / "scene_gt.json")[str(im_id)]
        depth = np.asarray(Image.open(scene / "depth" / f"{im_id:06d}.png"), dtype=np.float64) * camera["depth_scale"]
        image_rows, image_time = [], 0.0
        for instance, gt in enumerate(gts):
            obj_id = gt["obj_id"]
            if wanted and obj_id not in wanted:
                continue
            mask = np.asarray(Image.open(scene / "mask_visib" / f"{im_id:06d}_{instance:06d}.png")) > 0
            t0 = time.monotonic()
            observed = observed_cloud(depth, mask, camera["cam_K"])
            if len(observed.points) < args.min_points:
                continue
            diameter = info[str(obj_id)]["diameter"] / 1000.0
            if obj_id not in models:
                models[obj_id] = model_cloud(models_dir, obj_id)
            pose, fitness = register(models[obj_id], observed, diameter / VOXELS_PER_DIAMETER)
            image_time += time.monotonic() - t0
            image_rows.append((scene_id, im_id, obj_id, fitness, pose))
        for scene_id_, im_id_, obj_id, fitness, pose in image_rows:
            r = " ".join(f"{v:.8f}" for v in pose[:3, :3].reshape(-1))
            t = " ".join(f"{v * 1000.0:.4f}" for v in pose[:3, 3])
            rows.append(f"{scene_id_},{im_id_},{obj_id},{fitness:.6f},{r},{t},{image_time:.6f}")
        if (n + 1) % 10 == 0 or n + 1 == len(images):
            print(f"{n + 1}/{len(images)} images, {len(rows)} estimates, {time.monotonic() - started:.0f} s", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "".join(row + "\n" for row in rows))
    print(f"wrote {out} ({len(rows)} estimates)")


if __name__ == "__main__":
    main()
