//! Observations of rendered scenes against the ground truth: points on the
//! model surface, token masks covering the object's projection.

use std::path::PathBuf;

use nalgebra::Point3;
use parry3d::query::PointQuery;
use poseflow_contracts::MessageHeader;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_ingest::sources::{BopFrames, FrameSource, Masks, mask_file};
use poseflow_ingest::{IngestParams, check_frame, prepare};
use poseflow_scene::ModelLibrary;
use poseflow_scene::bop::{self, ByImage, GtEntry, GtInfoEntry, SceneDir};
use poseflow_scene::camera_path::CameraPath;
use poseflow_scene::dataset::{RenderSpec, lmo_camera, write_dataset};
use poseflow_scene::scene::{Occlusion, ViewRange};

fn objects_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo"))
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("poseflow-ingest-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn points_lie_on_the_model_and_tokens_cover_the_projection() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    let spec = RenderSpec {
        split: "test".into(),
        first_scene: 0,
        scenes: 2,
        frames_per_scene: 3,
        seed: 5,
        occlusion: Occlusion::Medium,
        camera: lmo_camera(640, 480),
        views: ViewRange { distance: (0.4, 1.0), ..ViewRange::default() },
        path: CameraPath::Random,
        depth_noise: None,
        rgb_noise: 0.0,
        sensor: None,
        style: Default::default(),
        condition: None,
    };
    let root = scratch("surface");
    write_dataset(&library, &spec, &root, |_| {}).unwrap();
    let params = IngestParams { image_size: 112, patch_grid: 8, ..IngestParams::default() };
    let trimeshes: Vec<_> = library.objects.iter().map(|o| (o.obj_id, o.model.mesh.to_trimesh().unwrap())).collect();
    let mut frames = BopFrames::open(&root, "test", &[], None, Masks::GroundTruth).unwrap();
    assert_eq!(frames.len(), 6);
    let (mut observed, mut covered_objects) = (0, 0);
    let mut rng = seeded_rng(1);
    while let Some(loaded) = frames.next_frame() {
        let loaded = loaded.unwrap();
        check_frame(&loaded.frame).unwrap();
        assert!(loaded.skipped.is_empty());
        let (scene_id, im_id) = ((loaded.frame.frame_id / 3) as u32, (loaded.frame.frame_id % 3) as u32);
        let dir = SceneDir::new(&root.join("test"), scene_id);
        let gts: ByImage<Vec<GtEntry>> = bop::read_json(&dir.scene_gt()).unwrap();
        let infos: ByImage<Vec<GtInfoEntry>> = bop::read_json(&dir.scene_gt_info()).unwrap();
        for object in &loaded.objects {
            let Ok(prepared) = prepare(&loaded.frame, object, &params, &mut rng) else {
                // Hidden or off-image objects are rejected, and only those.
                assert!(infos[&im_id][object.instance].px_count_visib < params.min_mask_pixels as u64);
                continue;
            };
            let pose = gts[&im_id][object.instance].pose(&dir.scene_gt(), im_id, object.instance).unwrap();
            let object_from_camera = pose.inverse();
            let mesh = &trimeshes.iter().find(|(id, _)| *id == object.obj_id).unwrap().1;
            let mut distances: Vec<f32> = prepared
                .points
                .iter()
                .map(|p| {
                    let camera_point = (p + prepared.centroid.coords).cast::<f64>();
                    let local = object_from_camera.transform_point(&camera_point).cast::<f32>();
                    mesh.distance_to_local_point(&local, true)
                })
                .collect();
            distances.sort_by(f32::total_cmp);
            let median = distances[distances.len() / 2];
            assert!(median < 0.002, "scene {scene_id} image {im_id} object {}: median {median} m", object.obj_id);
            let mean = prepared.points.iter().map(|p| p.coords).sum::<nalgebra::Vector3<f32>>() / 1024.0;
            assert!(mean.norm() < 1e-5, "points are not centred: {mean}");
            observed += 1;

            // Every model vertex of an unoccluded object projects into a
            // patch the token mask marks.
            if infos[&im_id][object.instance].visib_fract < 1.0 {
                continue;
            }
            let header = prepared.header(loaded.frame.frame_id, &loaded.frame.camera, &params);
            let mut payload = vec![0.0; header.payload_len().unwrap()];
            prepared.write_payload(&loaded.frame, object, &params, &mut payload);
            let tokens = header.view(&payload).unwrap().token_mask;
            let crop = prepared.crop;
            let grid = params.patch_grid as f64;
            let mesh_vertices =
                &library.objects.iter().find(|o| o.obj_id == object.obj_id).unwrap().model.mesh.vertices;
            let (mut inside, mut total) = (0, 0);
            for v in mesh_vertices {
                let Some((u, v)) = loaded.frame.camera.project(&pose.transform_point(&Point3::from(v.coords.cast())))
                else {
                    continue;
                };
                let (w, h) = (f64::from(loaded.frame.camera.width), f64::from(loaded.frame.camera.height));
                if !(-0.5..w - 0.5).contains(&u) || !(-0.5..h - 0.5).contains(&v) {
                    continue;
                }
                let (c, r) = ((u - crop.x_min) / crop.side * grid, (v - crop.y_min) / crop.side * grid);
                total += 1;
                if (0.0..grid).contains(&c) && (0.0..grid).contains(&r) {
                    inside += usize::from(tokens[r as usize * params.patch_grid as usize + c as usize] == 1.0);
                }
            }
            assert!(inside as f64 >= 0.99 * total as f64, "{inside} of {total} vertices on marked patches");
            // Without RGB: the same points, no image and no token to attend to.
            let depth_only = IngestParams { rgb: false, ..params.clone() };
            let mut blind = vec![1.0; payload.len()];
            prepared.write_payload(&loaded.frame, object, &depth_only, &mut blind);
            let blind_view = header.view(&blind).unwrap();
            assert!(blind_view.image.iter().chain(blind_view.token_mask).all(|&v| v == 0.0));
            assert_eq!(blind_view.points, header.view(&payload).unwrap().points);
            covered_objects += 1;
        }
    }
    assert!(observed >= 10 && covered_objects >= 3, "{observed} observations, {covered_objects} checked for cover");
    std::fs::remove_dir_all(&root).unwrap();
}

/// Masks from files (as a detector run offline writes them) give the same
/// objects as the ground truth, without reading `scene_gt.json`.
#[test]
fn mask_files_replace_the_ground_truth() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    let spec = RenderSpec {
        split: "val".into(),
        first_scene: 0,
        scenes: 1,
        frames_per_scene: 2,
        seed: 2,
        occlusion: Occlusion::Low,
        camera: lmo_camera(160, 120),
        views: ViewRange::default(),
        path: CameraPath::Random,
        depth_noise: None,
        rgb_noise: 0.0,
        sensor: None,
        style: Default::default(),
        condition: None,
    };
    let root = scratch("mask-files");
    write_dataset(&library, &spec, &root, |_| {}).unwrap();
    let scene = SceneDir::new(&root.join("val"), 0);
    let gts: ByImage<Vec<GtEntry>> = bop::read_json(&scene.scene_gt()).unwrap();
    let masks = root.join("detections");
    std::fs::create_dir_all(masks.join("000000")).unwrap();
    // Image 1 only, and only objects 11 and 1 (in that order of writing).
    for (k, gt) in gts[&1].iter().enumerate().filter(|(_, gt)| gt.obj_id != 10) {
        std::fs::copy(scene.mask_visib(1, k), mask_file(&masks, 0, 1, gt.obj_id)).unwrap();
    }
    std::fs::remove_file(scene.scene_gt()).unwrap();
    let mut frames = BopFrames::open(&root, "val", &[], None, Masks::Files(masks.clone())).unwrap();
    let first = frames.next_frame().unwrap().unwrap();
    assert!(first.objects.is_empty() && first.skipped.is_empty(), "image 0 has no mask files");
    let second = frames.next_frame().unwrap().unwrap();
    let found: Vec<(u32, usize)> = second.objects.iter().map(|o| (o.obj_id, o.instance)).collect();
    assert_eq!(found, [(1, 0), (11, 1)]);
    let expected = bop::read_mask_png(&scene.mask_visib(1, 0)).unwrap();
    assert_eq!(second.objects[0].mask, expected);
    let err = BopFrames::open(&root, "val", &[], None, Masks::Files(root.join("nowhere")))
        .unwrap()
        .next_frame()
        .unwrap()
        .unwrap_err()
        .to_string();
    assert!(err.contains("nowhere/000000"), "{err}");
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn test_targets_restrict_only_the_test_split() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    let spec = |split: &str, first_scene, frames_per_scene| RenderSpec {
        split: split.into(),
        first_scene,
        scenes: 1,
        frames_per_scene,
        seed: 3,
        occlusion: Occlusion::Low,
        camera: lmo_camera(160, 120),
        views: ViewRange::default(),
        path: CameraPath::Random,
        depth_noise: None,
        rgb_noise: 0.0,
        sensor: None,
        style: Default::default(),
        condition: None,
    };
    let root = scratch("targets");
    write_dataset(&library, &spec("test", 7, 2), &root, |_| {}).unwrap();
    write_dataset(&library, &spec("train", 0, 3), &root, |_| {}).unwrap();
    assert!(root.join("test_targets_bop19.json").is_file());
    // The targets name scene 7 only; the train split's scene 0 is still read.
    assert_eq!(BopFrames::open(&root, "test", &[], None, Masks::GroundTruth).unwrap().len(), 2);
    assert_eq!(BopFrames::open(&root, "train", &[], None, Masks::GroundTruth).unwrap().len(), 3);
    // A targets file of the caller's replaces the dataset's, for any split,
    // and the frame ids follow its order.
    let own = root.join("own_targets.json");
    std::fs::write(&own, r#"[{"scene_id": 0, "im_id": 2, "obj_id": 1, "inst_count": 1}]"#).unwrap();
    let frames = BopFrames::open(&root, "train", &[], Some(&own), Masks::GroundTruth).unwrap();
    assert_eq!(frames.images().collect::<Vec<_>>(), [(0, 2, &[1][..])]);
    let test = BopFrames::open(&root, "test", &[], None, Masks::GroundTruth).unwrap();
    let images: Vec<(u32, u32)> = test.images().map(|(scene, im, _)| (scene, im)).collect();
    assert_eq!(images, [(7, 0), (7, 1)]);
    // A target the image has no annotation of (as in real BOP releases) is
    // counted as skipped, naming the file; the annotated one is read.
    std::fs::write(
        &own,
        r#"[{"scene_id": 0, "im_id": 2, "obj_id": 1, "inst_count": 1}, {"scene_id": 0, "im_id": 2, "obj_id": 77, "inst_count": 1}]"#,
    )
    .unwrap();
    let mut frames = BopFrames::open(&root, "train", &[], Some(&own), Masks::GroundTruth).unwrap();
    let loaded = frames.next_frame().unwrap().unwrap();
    assert_eq!(loaded.objects.iter().map(|o| o.obj_id).collect::<Vec<_>>(), [1]);
    assert_eq!(loaded.skipped.len(), 1);
    let skipped = loaded.skipped[0].to_string();
    assert!(
        skipped.contains("object 77") && skipped.contains("scene_gt.json") && skipped.contains("no annotation"),
        "{skipped}"
    );
    std::fs::remove_dir_all(&root).unwrap();
}
