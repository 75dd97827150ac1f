//! `poseflow annotate-category`: records where a model's canonical category
//! frame lies, so that a mesh not made in that frame (a scanned YCB mug, a
//! BOP dataset's can) can be scored and rendered as a category instance.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use nalgebra::Vector3;
use poseflow_scene::category::{CATEGORIES_FILE, Category, annotate, any_front, canonical_frame};
use poseflow_scene::{load_bop_model, model_file_name};

use crate::import_model::parse_axis;

#[derive(Debug, Args)]
pub struct AnnotateCategoryArgs {
    /// BOP models directory holding the object (its categories.json is created or updated; other entries are kept).
    #[arg(long)]
    pub models: PathBuf,
    /// The object's id in that directory.
    #[arg(long)]
    pub obj_id: u32,
    /// Its category: mug, bowl, bottle or can.
    #[arg(long)]
    pub category: Category,
    /// Model-frame direction "X,Y,Z" from the object's base to its top: the canonical +y.
    #[arg(long, value_parser = parse_axis)]
    pub up: Vector3<f64>,
    /// Model-frame direction "X,Y,Z" of the canonical +x: where a mug's handle points (required for a mug). The
    /// other categories' turn about their axis is not scored, so it defaults to the model axis most across --up.
    #[arg(long, value_parser = parse_axis)]
    pub front: Option<Vector3<f64>>,
}

pub fn run(args: &AnnotateCategoryArgs) -> anyhow::Result<()> {
    let front = match (args.front, args.category) {
        (Some(front), _) => front,
        (None, Category::Mug) => bail!("--category mug needs --front: the model-frame direction its handle points"),
        (None, _) => any_front(&args.up),
    };
    let info_path = args.models.join("models_info.json");
    let info = poseflow_geometry::models_info::ModelsInfo::from_path(&info_path)
        .with_context(|| format!("--models {}", args.models.display()))?;
    let diameter = info
        .get(args.obj_id)
        .with_context(|| format!("{}: no object {} (--obj-id)", info_path.display(), args.obj_id))?
        .diameter;
    let mesh = load_bop_model(&args.models.join(model_file_name(args.obj_id)), diameter)?;
    let frame = canonical_frame(&mesh, &args.up, &front).context("--up/--front")?;
    let entry = annotate(&args.models, args.obj_id, args.category, &frame)?;
    let size = entry.size * 1e3;
    let (axis, angle) =
        frame.canonical_from_model.rotation.axis_angle().map_or((Vector3::z(), 0.0), |(a, t)| (a.into_inner(), t));
    let centre = -(frame.canonical_from_model.rotation.inverse() * frame.canonical_from_model.translation) * 1e3;
    println!(
        "object {} is a {}: size {:.1} x {:.1} x {:.1} mm (canonical x, y, z); canonical frame turned {:.0}° about ({:.3}, {:.3}, {:.3}), its origin at ({:.1}, {:.1}, {:.1}) mm in the model frame",
        args.obj_id,
        args.category.name(),
        size.x,
        size.y,
        size.z,
        angle.to_degrees(),
        axis.x,
        axis.y,
        axis.z,
        centre.x,
        centre.y,
        centre.z
    );
    if let Some(beyond_x) = entry.handle_beyond_x {
        println!("  handle: canonical x beyond {:.1} mm", beyond_x * 1e3);
    }
    println!("written to {}", args.models.join(CATEGORIES_FILE).display());
    Ok(())
}
