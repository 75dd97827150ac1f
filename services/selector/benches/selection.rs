//! Criterion benchmarks of the selector's kernels at the default sizes: 50
//! hypotheses, DBSCAN with the paper's thresholds, Chamfer and SDF scores
//! against 1024 observed points, refinement of the kept 10 hypotheses.
//! The object is the vendored LM-O ape. `cargo bench -p poseflow-selector`.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};
use poseflow_geometry::sampling::seeded_rng;
use poseflow_geometry::{Pose, so3};
use poseflow_scene::sdf_refine::{Likelihood, refine};
use poseflow_scene::{ObjectGeometry, load_mesh};
use poseflow_selector::cluster::{Neighbourhood, dbscan};
use poseflow_selector::score::Residuals;
use rand::Rng;

const HYPOTHESES: usize = 50;
const POINTS: usize = 1024;

fn ape() -> ObjectGeometry {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/lmo/obj_000001.ply");
    let mesh = load_mesh(&path, 1e-3).expect("the vendored ape model");
    ObjectGeometry::from_mesh(1, mesh.vertices, mesh.triangles, 64).expect("a closed mesh")
}

fn truth() -> Pose {
    Pose::new(so3::exp(&Vector3::new(0.4, -1.1, 0.6)), Vector3::new(0.03, -0.05, 0.75))
}

/// Hypotheses in three modes around the true pose (a symmetric-looking
/// spread plus outliers), as a flow's samples look.
fn hypotheses() -> Vec<Pose> {
    let mut rng = seeded_rng(1);
    let centre = truth();
    let flips = [Vector3::zeros(), Vector3::new(0.0, 0.0, std::f64::consts::PI), Vector3::new(1.5, 0.0, 0.0)];
    (0..HYPOTHESES)
        .map(|i| {
            let mode = so3::exp(&flips[i % 3]);
            let turn = Vector3::from_fn(|_, _| rng.random_range(-0.08..0.08));
            let shift = Vector3::from_fn(|_, _| rng.random_range(-0.008..0.008));
            Pose::new(centre.rotation * mode * so3::exp(&turn), centre.translation + shift)
        })
        .collect()
}

/// Observed points: model vertices under the true pose with 2 mm noise.
fn observed(object: &ObjectGeometry) -> Vec<Point3<f64>> {
    let mut rng = seeded_rng(2);
    let vertices = object.mesh.vertices();
    let pose = truth();
    (0..POINTS)
        .map(|i| {
            let v = vertices[i * vertices.len() / POINTS].coords.cast::<f64>();
            let noise = Vector3::from_fn(|_, _| rng.random_range(-0.002..0.002));
            pose.transform_point(&Point3::from(v + noise))
        })
        .collect()
}

fn selection(c: &mut Criterion) {
    let poses = hypotheses();
    let neighbourhood = Neighbourhood { rotation: 10f64.to_radians(), translation: 0.02, min_samples: 3 };
    c.bench_function("dbscan/50_poses", |b| b.iter(|| dbscan(black_box(&poses), &neighbourhood)));

    let object = ape();
    object.grid();
    let points = observed(&object);
    let likelihood = Likelihood { noise_std: 0.005, outlier_distance: 0.02 };
    for (name, residuals) in [("chamfer", Residuals::Chamfer(&object)), ("sdf", Residuals::Sdf(&object))] {
        c.bench_function(&format!("{name}_score/50_poses_x_1024_points"), |b| {
            b.iter(|| poses.iter().map(|pose| residuals.score(pose, black_box(&points), &likelihood)).sum::<f64>())
        });
    }
    let kept = &poses[..HYPOTHESES / 5];
    c.bench_function("refine/10_poses_x_1024_points", |b| {
        b.iter(|| {
            let refined: Vec<Pose> =
                kept.iter().map(|pose| refine(object.grid(), pose, black_box(&points), &likelihood, 10).pose).collect();
            refined
        })
    });
}

criterion_group!(benches, selection);
criterion_main!(benches);
