//! `poseflow sim`: closed-loop simulations on rendered scenes, with the
//! real pose stages run in-process.

mod clutter;
mod grasp;
mod mug;
mod nbv;

use std::path::Path;

use anyhow::Context;
use clap::{Args, Subcommand};
use poseflow_geometry::sampling::SeededRng;
use poseflow_inference::stage::InferenceParams;
use poseflow_ingest::IngestParams;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_pipeline::PosePipeline;
use poseflow_sampler::SamplerParams;
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, DepthNoise, Frame};
use poseflow_selector::SelectorParams;

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

/// A stage's parameters: its config file with `overrides` laid over it.
fn stage_params(config: &Path, stage: &str, overrides: serde_json::Value) -> anyhow::Result<serde_json::Value> {
    let path = config.join(format!("{stage}.toml"));
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}: cannot read", path.display()))?;
    let table: toml::Table = toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
    let mut params = serde_json::to_value(table)?;
    if let (Some(params), Some(overrides)) = (params.as_object_mut(), overrides.as_object()) {
        params.extend(overrides.clone());
    }
    Ok(params)
}

/// The pose stages as the simulations estimate with them: the graph's
/// config with the default model's input size, `model`, and SDF selection
/// with refinement against the models in `objects`.
fn pose_pipeline(config: &Path, model: &Path, objects: &Path) -> anyhow::Result<PosePipeline> {
    let ingest = IngestParams::from_json(&stage_params(
        config,
        "ingest",
        serde_json::json!({"image_size": 112, "patch_grid": 8}),
    )?)?;
    let inference =
        InferenceParams::from_json(&stage_params(config, "inference", serde_json::json!({"model": model}))?)?;
    let sampler = SamplerParams::from_json(&stage_params(config, "sampler", serde_json::json!({}))?)?;
    let selector = SelectorParams::from_json(&stage_params(
        config,
        "selector",
        serde_json::json!({"method": "sdf", "models": objects, "refine": true}),
    )?)?;
    Ok(PosePipeline::new(ingest, &inference, sampler, selector)?)
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
