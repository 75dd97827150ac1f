//! `poseflow sim`: closed-loop simulations on rendered scenes, with the
//! pose stages of a graph file run in-process (built by their
//! registrations, as in every graph).

mod clutter;
mod grasp;
mod mug;
mod nbv;

use std::path::Path;

use anyhow::Context;
use clap::{Args, Subcommand};
use poseflow_geometry::sampling::SeededRng;
use poseflow_graph::Graph;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_nbv::PoseStages;
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, DepthNoise, Frame};

#[derive(Debug, Args)]
pub struct SimArgs {
    #[command(subcommand)]
    pub command: SimCommand,
}

#[derive(Debug, Subcommand)]
pub enum SimCommand {
    /// Grasp a mug with its handle visible or hidden: single pose hypothesis vs the marginalised grasp flow.
    Grasp(grasp::GraspSimArgs),
    /// Start from an ambiguous view (mug handle hidden, object in clutter): move to the next-best view, a random view, or stay; compare uncertainty and error.
    Nbv(nbv::NbvSimArgs),
}

pub fn run(args: &SimArgs) -> anyhow::Result<()> {
    match &args.command {
        SimCommand::Grasp(args) => grasp::run(args),
        SimCommand::Nbv(args) => nbv::run(args),
    }
}

/// A graph file read for an in-process run (its stages are built from the
/// registry, so their executables need not exist).
fn load_graph(file: &Path) -> anyhow::Result<Graph> {
    let text = std::fs::read_to_string(file).with_context(|| format!("{}: cannot read", file.display()))?;
    Ok(poseflow_graph::parse_in_process(&text, file)?)
}

/// A stage's parameters in `graph` with `overrides` laid over them.
fn stage_params(graph: &Graph, stage: &str, overrides: serde_json::Value) -> anyhow::Result<serde_json::Value> {
    let known = || graph.stages.keys().cloned().collect::<Vec<_>>().join(", ");
    let stage = graph.stages.get(stage).with_context(|| {
        format!("{}: no stage `{stage}`; the simulation needs one (stages: {})", graph.file.display(), known())
    })?;
    let mut params = stage.params.clone();
    if let (Some(params), Some(overrides)) = (params.as_object_mut(), overrides.as_object()) {
        params.extend(overrides.clone());
    }
    Ok(params)
}

/// The pose stages of `graph` as the simulations estimate with them, in
/// this process: `model`, and SDF selection with refinement against the
/// models in `objects`.
fn pose_stages(graph: &Graph, model: &Path, objects: &Path) -> anyhow::Result<PoseStages> {
    let mut graph = graph.clone();
    graph.set("inference", &["model"], serde_json::json!(model))?;
    graph.set("selector", &["method"], "sdf".into())?;
    graph.set("selector", &["models"], serde_json::json!(objects))?;
    graph.set("selector", &["refine"], true.into())?;
    Ok(PoseStages::start(&graph, &PoseStages::registry())?)
}

/// What a simulated camera delivers: `rendered` with the sensor's depth
/// noise, labelled `label`, and the mask of the object (`obj_id`,
/// `instance`) on the `visible` pixels.
fn sensor_frame(
    camera: Camera,
    frame_id: u64,
    label: String,
    rendered: Frame,
    (obj_id, instance, visible): (u32, usize, Vec<bool>),
    rng: &mut SeededRng,
) -> (RgbdFrame, ObjectMask) {
    let depth = DepthNoise::default().apply(&rendered.depth, camera.width as usize, rng);
    let (width, height) = (camera.width, camera.height);
    let frame = RgbdFrame {
        frame_id,
        label,
        camera,
        rgb: Raster { width, height, pixels: rendered.rgb },
        depth: Raster { width, height, pixels: depth },
    };
    (frame, ObjectMask { obj_id, instance, mask: Raster { width, height, pixels: visible } })
}

/// `value` rounded to `decimals` places: the precision a trials table
/// carries (the CSV writer prints the shortest form of what it is given).
fn rounded(value: f64, decimals: i32) -> f64 {
    let scale = 10f64.powi(decimals);
    (value * scale).round() / scale
}

/// Writes `rows` as `<out>/trials.csv` with a header from the row type's
/// field names.
fn write_trials_csv<R: serde::Serialize>(
    out: &std::path::Path,
    rows: impl IntoIterator<Item = R>,
) -> anyhow::Result<()> {
    use anyhow::Context;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let path = out.join("trials.csv");
    let mut writer = csv::Writer::from_path(&path).with_context(|| format!("{}: cannot create", path.display()))?;
    for row in rows {
        writer.serialize(row).with_context(|| format!("{}: cannot write", path.display()))?;
    }
    writer.flush().with_context(|| format!("{}: cannot write", path.display()))
}
