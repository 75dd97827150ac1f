//! A rendered dataset read back: poses and intrinsics survive the files,
//! visible masks match an independent rasterisation of the model under the
//! ground-truth pose, and noiseless depth lies on the model surface.

use std::path::{Path, PathBuf};

use nalgebra::Point3;
use parry3d::query::PointQuery;
use poseflow_geometry::Pose;
use poseflow_scene::bop::{self, ByImage, CameraEntry, DatasetCamera, GtEntry, GtInfoEntry, SceneDir};
use poseflow_scene::camera_path::CameraPath;
use poseflow_scene::dataset::{RenderSpec, frame, lmo_camera, scene, write_dataset};
use poseflow_scene::scene::{Occlusion, ViewRange};
use poseflow_scene::{Camera, ModelLibrary, ObjectMesh};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("poseflow-dataset-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn clean_spec() -> RenderSpec {
    RenderSpec {
        split: "test".into(),
        first_scene: 3,
        scenes: 2,
        frames_per_scene: 3,
        seed: 11,
        occlusion: Occlusion::Low,
        camera: lmo_camera(320, 240),
        views: ViewRange { distance: (0.35, 0.8), ..ViewRange::default() },
        path: CameraPath::Random,
        depth_noise: None,
        rgb_noise: 0.0,
        sensor: None,
        style: Default::default(),
        condition: None,
    }
}

/// Pixels whose centre lies inside the projection of some triangle: a
/// scan-conversion independent of the ray caster.
fn rasterise(mesh: &ObjectMesh, pose: &Pose, camera: &Camera) -> Vec<bool> {
    let (w, h) = (camera.width as i64, camera.height as i64);
    let mut mask = vec![false; (w * h) as usize];
    let projected: Vec<Option<(f64, f64)>> =
        mesh.vertices.iter().map(|v| camera.project(&pose.transform_point(&v.cast::<f64>()))).collect();
    for t in &mesh.triangles {
        let [Some(a), Some(b), Some(c)] = t.map(|i| projected[i as usize]) else { continue };
        let edge = |p: (f64, f64), q: (f64, f64), x: f64, y: f64| (q.0 - p.0) * (y - p.1) - (q.1 - p.1) * (x - p.0);
        let area = edge(a, b, c.0, c.1);
        if area == 0.0 {
            continue;
        }
        let (u0, u1) = (a.0.min(b.0).min(c.0).ceil() as i64, a.0.max(b.0).max(c.0).floor() as i64);
        let (v0, v1) = (a.1.min(b.1).min(c.1).ceil() as i64, a.1.max(b.1).max(c.1).floor() as i64);
        for v in v0.max(0)..=v1.min(h - 1) {
            for u in u0.max(0)..=u1.min(w - 1) {
                let (x, y) = (u as f64, v as f64);
                let signs = [edge(a, b, x, y), edge(b, c, x, y), edge(c, a, x, y)].map(|e| e * area.signum() >= 0.0);
                if signs.iter().all(|&inside| inside) {
                    mask[(v * w + u) as usize] = true;
                }
            }
        }
    }
    mask
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let both = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let either = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    both as f64 / either.max(1) as f64
}

fn objects_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo"))
}

#[test]
fn rendered_dataset_reads_back_consistently() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    assert_eq!(library.objects.iter().map(|o| o.obj_id).collect::<Vec<_>>(), [1, 10, 11]);
    let spec = clean_spec();
    let out = scratch("round-trip");
    let mut frames = 0;
    write_dataset(&library, &spec, &out, |_| frames += 1).unwrap();
    assert_eq!(frames, 6);

    let root_camera: DatasetCamera = bop::read_json(&out.join("camera.json")).unwrap();
    assert_eq!(root_camera, DatasetCamera::new(&spec.camera, 0.1));
    let targets: Vec<serde_json::Value> = bop::read_json(&out.join("test_targets_bop19.json")).unwrap();
    assert_eq!(targets.len(), 6 * 3);
    assert!(out.join("models/obj_000010.ply").is_file() && out.join("models/models_info.json").is_file());

    let trimeshes: Vec<_> = library.objects.iter().map(|o| o.model.mesh.to_trimesh().unwrap()).collect();
    let (mut unoccluded, mut depth_pixels) = (0, 0);
    for scene_id in 3..5 {
        let dir = SceneDir::new(&out.join("test"), scene_id);
        let cameras: ByImage<CameraEntry> = bop::read_json(&dir.scene_camera()).unwrap();
        let gts: ByImage<Vec<GtEntry>> = bop::read_json(&dir.scene_gt()).unwrap();
        let infos: ByImage<Vec<GtInfoEntry>> = bop::read_json(&dir.scene_gt_info()).unwrap();
        let truth = scene(&library, &spec, scene_id);
        for im_id in 0..3 {
            let rendered = frame(&library, &spec, &truth, scene_id, im_id).unwrap();
            let entry = &cameras[&im_id];
            let camera = entry.camera(320, 240, &dir.scene_camera(), im_id).unwrap();
            assert_eq!(camera, spec.camera);
            let camera_from_world = entry.camera_from_world(&dir.scene_camera(), im_id).unwrap().unwrap();
            assert_close(&camera_from_world, &rendered.camera_from_world);
            let depth = bop::read_depth_png(&dir.depth(im_id), entry.depth_scale).unwrap();
            for (k, gt) in gts[&im_id].iter().enumerate() {
                let object = &library.objects[truth.objects[k].library_index];
                assert_eq!(gt.obj_id, object.obj_id);
                let pose = gt.pose(&dir.scene_gt(), im_id, k).unwrap();
                assert_close(&pose, &rendered.view.object_poses[k]);
                let visible = bop::read_mask_png(&dir.mask_visib(im_id, k)).unwrap().pixels;
                let info = &infos[&im_id][k];
                assert_eq!(info.px_count_visib, visible.iter().filter(|&&v| v).count() as u64);
                if info.visib_fract == 1.0 && info.px_count_all > 100 {
                    let projected = rasterise(&object.model.mesh, &pose, &camera);
                    let overlap = iou(&visible, &projected);
                    assert!(overlap >= 0.95, "scene {scene_id} image {im_id} object {}: IoU {overlap}", gt.obj_id);
                    unoccluded += 1;
                }
                let object_from_camera = pose.inverse();
                for (i, _) in visible.iter().enumerate().filter(|(_, v)| **v) {
                    let z = f64::from(depth.pixels[i]);
                    let (u, v) = ((i % 320) as f64, (i / 320) as f64);
                    let p = Point3::new((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z);
                    let local = object_from_camera.transform_point(&p).cast::<f32>();
                    let on_surface = trimeshes[truth.objects[k].library_index].distance_to_local_point(&local, true);
                    assert!(on_surface < 1e-3, "scene {scene_id} image {im_id} pixel {i}: {on_surface} m off");
                    depth_pixels += 1;
                }
            }
        }
    }
    assert!(unoccluded >= 3, "too few unoccluded objects to check masks: {unoccluded}");
    assert!(depth_pixels > 5000, "{depth_pixels}");
    std::fs::remove_dir_all(&out).unwrap();
}

fn assert_close(read: &Pose, written: &Pose) {
    assert!((read.rotation.matrix() - written.rotation.matrix()).abs().max() < 1e-12, "{read:?} vs {written:?}");
    assert!((read.translation - written.translation).norm() < 1e-12, "{read:?} vs {written:?}");
}

#[test]
fn every_object_rests_on_the_plane_and_none_overlap() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    for (occlusion, seed) in [(Occlusion::Low, 1), (Occlusion::Medium, 2), (Occlusion::High, 3)] {
        let spec = RenderSpec { occlusion, seed, ..clean_spec() };
        for scene_id in 0..5 {
            let scene = scene(&library, &spec, scene_id);
            let mut footprints = Vec::new();
            for object in &scene.objects {
                let mesh = &library.objects[object.library_index].model.mesh;
                let world: Vec<Point3<f64>> =
                    mesh.vertices.iter().map(|v| object.world_from_object.transform_point(&v.cast())).collect();
                let lowest = world.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
                assert!(lowest.abs() < 1e-6, "{occlusion:?} scene {scene_id}: lowest point at {lowest} m");
                let centre = object.world_from_object.translation.xy();
                let radius = world.iter().map(|p| (p.coords.xy() - centre).norm()).fold(0.0, f64::max);
                footprints.push((centre, radius));
            }
            for (i, (a, ra)) in footprints.iter().enumerate() {
                for (b, rb) in &footprints[i + 1..] {
                    assert!((a - b).norm() >= ra + rb - 1e-9, "{occlusion:?} scene {scene_id}: footprints overlap");
                }
            }
        }
    }
}

#[test]
fn more_occlusion_means_less_of_each_object_visible() {
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    let mean_visibility = |occlusion| {
        let spec =
            RenderSpec { occlusion, scenes: 1, frames_per_scene: 1, camera: lmo_camera(160, 120), ..clean_spec() };
        let (mut sum, mut count) = (0.0, 0);
        for scene_id in 0..8 {
            let truth = scene(&library, &spec, scene_id);
            for im_id in 0..3 {
                let rendered = frame(&library, &spec, &truth, scene_id, im_id).unwrap();
                for (k, full) in rendered.view.silhouettes.iter().enumerate() {
                    let all = full.iter().filter(|&&v| v).count();
                    let visible = rendered.view.frame.label.iter().filter(|&&l| usize::from(l) == k + 1).count();
                    if all > 0 {
                        sum += visible as f64 / all as f64;
                        count += 1;
                    }
                }
            }
        }
        sum / f64::from(count)
    };
    let (low, high) = (mean_visibility(Occlusion::Low), mean_visibility(Occlusion::High));
    assert!(low > high + 0.05, "visible fraction: low occlusion {low:.3}, high {high:.3}");
}

#[test]
fn missing_models_and_unknown_ids_are_named() {
    let err = ModelLibrary::load(Path::new("/nonexistent/models"), &[]).unwrap_err().to_string();
    assert!(err.contains("/nonexistent/models/models_info.json"), "{err}");
    let err = ModelLibrary::load(&objects_dir(), &[1, 99]).unwrap_err().to_string();
    assert!(err.contains("object 99 is not listed"), "{err}");
    // Listed in models_info.json but not vendored.
    let err = ModelLibrary::load(&objects_dir(), &[5]).unwrap_err().to_string();
    assert!(err.contains("obj_000005.ply"), "{err}");
}

/// A model in the wrong units (a file in metres, a diameter in metres) is
/// refused with the file, both sizes and the likely cause named.
#[test]
fn models_in_the_wrong_units_are_refused() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/ycbv/mug-bowl");
    for (factor, hint) in [(1000.0, "model file looks like metres"), (0.001, "diameter looks like metres")] {
        let dir = scratch(&format!("units-{factor}"));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(source.join("obj_000014.ply"), dir.join("obj_000014.ply")).unwrap();
        let mut info: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(source.join("models_info.json")).unwrap()).unwrap();
        let diameter = info["14"]["diameter"].as_f64().unwrap();
        info["14"]["diameter"] = serde_json::json!(diameter * factor);
        std::fs::write(dir.join("models_info.json"), info.to_string()).unwrap();
        let err = ModelLibrary::load(&dir, &[14]).unwrap_err().to_string();
        assert!(err.contains("obj_000014.ply") && err.contains(hint), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
    assert!(ModelLibrary::load(&source, &[14]).is_ok());
}

/// `RenderSpec::condition`: every image drawn for the mug with its handle
/// hidden shows no handle and at least half the mug; with it visible, the
/// handle in view; the same seed gives the same views; an object that is
/// not in the scene is an error naming scene, image and condition.
#[test]
fn views_are_drawn_until_the_mug_handle_is_hidden_or_in_view() {
    use poseflow_scene::part::{ObjectPart, PartVisibility, ViewCondition};
    let ycbv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/ycbv/models");
    let library = ModelLibrary::load(&ycbv, &[14]).unwrap();
    let handle = ObjectPart::ycbv_mug_handle();
    let condition = |visibility| Some(ViewCondition::new(handle, visibility));
    let spec = |visibility| RenderSpec {
        scenes: 1,
        frames_per_scene: 3,
        camera: lmo_camera(160, 120),
        condition: condition(visibility),
        ..clean_spec()
    };
    let truth = scene(&library, &spec(PartVisibility::Hidden), 3);
    for (visibility, wanted) in [(PartVisibility::Hidden, 0..=0), (PartVisibility::Visible, 10..=usize::MAX)] {
        let spec = spec(visibility);
        for im_id in 0..3 {
            let rendered = frame(&library, &spec, &truth, 3, im_id).unwrap();
            let pixels = handle.visible_pixels(&rendered.view, &spec.camera, 0);
            assert!(wanted.contains(&pixels), "{visibility:?} image {im_id}: {pixels} handle pixels");
            let visible = rendered.view.frame.label.iter().filter(|&&l| l == 1).count();
            let all = rendered.view.silhouettes[0].iter().filter(|&&s| s).count();
            assert!(2 * visible >= all && all > 0, "{visible} of {all} mug pixels visible");
            let again = frame(&library, &spec, &truth, 3, im_id).unwrap();
            assert_eq!(again.camera_from_world, rendered.camera_from_world);
        }
    }
    let absent = RenderSpec {
        condition: Some(ViewCondition::new(ObjectPart { obj_id: 99, ..handle }, PartVisibility::Hidden)),
        ..spec(PartVisibility::Hidden)
    };
    let err = frame(&library, &absent, &truth, 3, 1).unwrap_err().to_string();
    assert!(err.contains("scene 3 image 1") && err.contains("object 99"), "{err}");
}

/// A scene whose arrangement no camera draw can show under the condition is
/// arranged again (from its own streams, so the dataset stays reproducible)
/// instead of failing the render, and `poseflow_render.json` names it; when
/// no arrangement can, the error names scene, image and condition.
#[test]
fn a_scene_no_view_can_show_is_arranged_again_and_recorded() {
    use poseflow_scene::dataset::arrangement;
    use poseflow_scene::part::{ObjectPart, PartVisibility, ViewCondition};
    let ycbv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/ycbv/models");
    let library = ModelLibrary::load(&ycbv, &[14]).unwrap();
    let handle = ObjectPart::ycbv_mug_handle();
    // Few camera draws per arrangement: some first arrangements fail.
    let hidden = ViewCondition { view_attempts: 3, ..ViewCondition::new(handle, PartVisibility::Hidden) };
    let spec = RenderSpec {
        scenes: 6,
        frames_per_scene: 1,
        camera: lmo_camera(160, 120),
        condition: Some(hidden),
        ..clean_spec()
    };
    let placements = |s: &poseflow_scene::scene::Scene| format!("{:?}", s.objects);
    assert_eq!(placements(&arrangement(&library, &spec, 3, 0)), placements(&scene(&library, &spec, 3)));
    assert_ne!(placements(&arrangement(&library, &spec, 3, 1)), placements(&scene(&library, &spec, 3)));

    let out = scratch("rearranged");
    write_dataset(&library, &spec, &out, |_| {}).unwrap();
    let provenance: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("poseflow_render.json")).unwrap()).unwrap();
    let rearranged: Vec<u64> = provenance["rearranged_scenes"]
        .as_array()
        .expect("some first arrangement failed its one draw")
        .iter()
        .map(|id| id.as_u64().unwrap())
        .collect();
    assert!(!rearranged.is_empty() && rearranged.iter().all(|id| (3..9).contains(id)), "{rearranged:?}");
    for scene_id in 3..9u32 {
        assert!(SceneDir::new(&out.join(&spec.split), scene_id).rgb(0).exists(), "scene {scene_id} was written");
    }

    let impossible = ViewCondition { view_attempts: 1, ..ViewCondition::new(handle, PartVisibility::Visible) };
    let never = RenderSpec {
        scenes: 1,
        condition: Some(ViewCondition { part: ObjectPart { beyond: 10.0, ..handle }, ..impossible }),
        ..spec
    };
    let err = write_dataset(&library, &never, &out, |_| {}).unwrap_err().to_string();
    assert!(err.contains("scene 3 image 0") && err.contains("no view in 1 random cameras"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}

/// A styled scene keeps the targets and clutter of the plain scene with the
/// same seed, adds unannotated distractors from the other objects (seen as
/// labels beyond the targets') and patterns the table and backdrop.
#[test]
fn styled_scenes_add_distractors_and_patterns_around_the_same_targets() {
    use poseflow_scene::scene::SceneStyle;
    let ycbv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/ycbv/models");
    let library = ModelLibrary::load(&ycbv, &[13, 14]).unwrap().with_distractors(&ycbv).unwrap();
    assert_eq!(library.distractors.len(), 19, "the 21 YCB-V objects but the two targets");
    let plain = clean_spec();
    let styled =
        RenderSpec { style: SceneStyle { textured: true, distractors: 3, ..SceneStyle::default() }, ..clean_spec() };
    let mut distractor_pixels = 0;
    for scene_id in 3..9 {
        let (a, b) = (scene(&library, &plain, scene_id), scene(&library, &styled, scene_id));
        let poses =
            |s: &poseflow_scene::scene::Scene| s.objects.iter().map(|o| o.world_from_object).collect::<Vec<_>>();
        assert_eq!(poses(&a), poses(&b), "scene {scene_id}: the targets stay put");
        assert!(b.clutter.len() >= a.clutter.len() && b.clutter.len() <= a.clutter.len() + 3);
        assert!(b.plane.texture.is_some() && b.backdrop.is_some() && a.plane.texture.is_none());
        let rendered = frame(&library, &styled, &b, scene_id, 0).unwrap();
        // Labels: targets 1..=2, then clutter in order (distractors last), then the table.
        let first_distractor = 2 + a.clutter.len() as u16 + 1;
        let last_distractor = 2 + b.clutter.len() as u16;
        distractor_pixels +=
            rendered.view.frame.label.iter().filter(|&&l| (first_distractor..=last_distractor).contains(&l)).count();
    }
    assert!(distractor_pixels > 100, "distractors in view: {distractor_pixels} pixels");
    let same = ModelLibrary::load(&ycbv, &[]).unwrap().with_distractors(&ycbv).unwrap_err().to_string();
    assert!(same.contains("no object is left"), "{same}");
}

/// A video with events: each occlusion hides its object wholly for some of
/// its images (the box covers the bounding sphere), each teleport turns
/// its object by 90-180° between two images while the camera moves 1°;
/// `video_events.json` lists them by object id.
#[test]
fn video_events_hide_and_move_their_objects() {
    use poseflow_scene::video::{EventRecord, VideoEvents};
    let library = ModelLibrary::load(&objects_dir(), &[]).unwrap();
    let out = scratch("video-events");
    let events = VideoEvents { occlusions: 2, teleports: 2 };
    let spec = RenderSpec {
        scenes: 1,
        frames_per_scene: 150,
        camera: lmo_camera(160, 120),
        path: CameraPath::Orbit { step_deg: 1.0, events },
        ..clean_spec()
    };
    write_dataset(&library, &spec, &out, |_| {}).unwrap();
    let dir = SceneDir::new(&out.join("test"), 3);
    let records: Vec<EventRecord> = bop::read_json(&dir.video_events()).unwrap();
    let gt: ByImage<Vec<GtEntry>> = bop::read_json(&dir.scene_gt()).unwrap();
    let info: ByImage<Vec<GtInfoEntry>> = bop::read_json(&dir.scene_gt_info()).unwrap();
    let index = |obj_id: u32| gt[&0].iter().position(|e| e.obj_id == obj_id).unwrap();
    let rotation = |im: u32, obj_id: u32| {
        let entries = &gt[&im];
        entries[index(obj_id)].pose(&dir.scene_gt(), im, index(obj_id)).unwrap().rotation
    };
    let (mut occlusions, mut teleports) = (0, 0);
    for record in &records {
        match *record {
            EventRecord::Occlusion { obj_id, start, end, hidden } => {
                occlusions += 1;
                let shares: Vec<f64> = (start..end).map(|im| info[&im][index(obj_id)].visib_fract).collect();
                let gone = shares.iter().filter(|&&share| share == 0.0).count() as u32;
                assert!(gone >= hidden.div_ceil(2), "hidden {hidden}, wholly hidden in {gone}: {shares:?}");
                assert!(shares[0] > 0.0 && shares[shares.len() - 1] > 0.0, "{shares:?}");
            }
            EventRecord::Teleport { obj_id, at, turn_deg, .. } => {
                teleports += 1;
                let jump = rotation(at - 1, obj_id).angle_to(&rotation(at, obj_id)).to_degrees();
                let before = rotation(at - 2, obj_id).angle_to(&rotation(at - 1, obj_id)).to_degrees();
                assert!((jump - turn_deg.abs()).abs() < 5.0 && before < 5.0, "{turn_deg}: {jump} after {before}");
            }
        }
    }
    assert!(occlusions >= 1 && teleports >= 1, "{records:?}");
    let _ = std::fs::remove_dir_all(&out);
}
