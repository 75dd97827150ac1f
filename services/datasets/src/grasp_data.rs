//! `poseflow grasp-data`: antipodal, collision-checked grasps for each
//! object of a BOP models directory, the training data of the grasp flow.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_grasp::data::GraspSet;
use poseflow_grasp::{Gripper, sample_grasps};
use poseflow_scene::surface_points;
use poseflow_scene::{ModelLibrary, oriented_trimesh};

#[derive(Debug, Args)]
pub struct GraspDataArgs {
    /// BOP models directory (models_info.json and obj_NNNNNN.ply files).
    #[arg(long)]
    pub models: PathBuf,
    /// Directory to write grasps_NNNNNN.json to (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Objects, e.g. 13,14 (default: every object with a model file).
    #[arg(long, value_delimiter = ',')]
    pub ids: Vec<u32>,
    /// Grasps to keep per object.
    #[arg(long, default_value_t = 2000)]
    pub grasps: usize,
    /// Give up on an object after this many antipodal proposals.
    #[arg(long, default_value_t = 400_000)]
    pub max_proposals: usize,
    /// Surface points written with each object (the grasp flow's condition).
    #[arg(long, default_value_t = 2048)]
    pub cloud_points: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

pub fn run(args: &GraspDataArgs) -> anyhow::Result<()> {
    // The Panda-like gripper; each file records the one it was made with.
    let gripper = Gripper::default();
    if args.grasps == 0 {
        bail!("--grasps 0: expected at least one grasp per object");
    }
    let library = ModelLibrary::load(&args.models, &args.ids)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("{}: cannot create", args.out.display()))?;
    for object in &library.objects {
        let started = Instant::now();
        let mesh = oriented_trimesh(object.model.mesh.vertices.clone(), object.model.mesh.triangles.clone())
            .with_context(|| format!("{}: cannot build a triangle mesh", object.path.display()))?;
        let mut rng = seeded_rng(args.seed.wrapping_mul(1_000_003).wrapping_add(u64::from(object.obj_id)));
        let sampled = sample_grasps(&mesh, &gripper, args.grasps, args.max_proposals, &mut rng);
        let cloud =
            surface_points(&mesh, args.cloud_points, &mut rng).into_iter().map(|(p, _)| p.coords.into()).collect();
        let set = GraspSet::new(object.obj_id, gripper, sampled.proposals, &sampled.grasps, cloud);
        let path = args.out.join(format!("grasps_{:06}.json", object.obj_id));
        std::fs::write(&path, serde_json::to_vec(&set)?)
            .with_context(|| format!("{}: cannot write", path.display()))?;
        println!(
            "object {:>3}: {:>5} grasps from {:>7} proposals ({:.1} %) in {:.1} s -> {}",
            object.obj_id,
            sampled.grasps.len(),
            sampled.proposals,
            100.0 * sampled.grasps.len() as f64 / sampled.proposals.max(1) as f64,
            started.elapsed().as_secs_f64(),
            path.display()
        );
        if sampled.grasps.is_empty() {
            tracing::warn!(object = object.obj_id, "no grasp holds: the object is wider than the gripper everywhere");
        }
    }
    Ok(())
}
