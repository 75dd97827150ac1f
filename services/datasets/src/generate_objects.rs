//! `poseflow generate-objects`: procedural mugs, bowls, bottles and cans
//! (`poseflow_scene::category`) written to a BOP models directory, each in
//! its category's canonical frame, for category-level data.

use std::path::PathBuf;

use clap::Args;
use poseflow_scene::category::{CATEGORIES_FILE, Category, write_instances};

#[derive(Debug, Args)]
pub struct GenerateObjectsArgs {
    /// BOP models directory to write to (created if missing; other objects are kept, the same ids replaced).
    #[arg(long)]
    pub models: PathBuf,
    /// Categories to generate, comma-separated: mug, bowl, bottle, can [default: all four].
    #[arg(long, value_delimiter = ',')]
    pub categories: Vec<Category>,
    /// Instances per category.
    #[arg(long, default_value_t = 10)]
    pub count: u32,
    /// Seeds every instance's shape and colours: the same seed, the same objects.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The first object id; the categories take consecutive ids in turn.
    #[arg(long, default_value_t = 1)]
    pub first_id: u32,
}

pub fn run(args: &GenerateObjectsArgs) -> anyhow::Result<()> {
    let categories = if args.categories.is_empty() { Category::ALL.to_vec() } else { args.categories.clone() };
    let written = write_instances(&categories, args.count, args.seed, args.first_id, &args.models)?;
    for w in &written {
        let size = w.generated.size * 1e3;
        println!(
            "{:>6}  {:<6}  size {:5.1} x {:5.1} x {:5.1} mm  {:>6} vertices  seed {}",
            w.obj_id,
            w.generated.category().name(),
            size.x,
            size.y,
            size.z,
            w.model.vertices,
            w.seed
        );
    }
    println!(
        "{} objects in {} (models_info.json, {CATEGORIES_FILE}); canonical frame: y up the symmetry axis, mug handles towards +x, centred",
        written.len(),
        args.models.display()
    );
    Ok(())
}
