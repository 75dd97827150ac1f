//! `poseflow import-model`: adds an object from a PLY or OBJ mesh to a BOP
//! models directory, so that it can be rendered and trained on.

use std::path::PathBuf;

use anyhow::bail;
use clap::Args;
use nalgebra::Vector3;
use poseflow_scene::import::{ImportSpec, import_model};
use poseflow_scene::symmetry::{Symmetry, turn};

#[derive(Debug, Args)]
pub struct ImportModelArgs {
    /// The mesh (.ply or .obj).
    #[arg(long)]
    pub mesh: PathBuf,
    /// BOP models directory to add it to (created if missing; other objects are kept).
    #[arg(long)]
    pub models: PathBuf,
    /// The object id it gets (written as obj_NNNNNN.ply).
    #[arg(long)]
    pub obj_id: u32,
    /// Units of the mesh file.
    #[arg(long, value_enum, default_value_t = Units::M)]
    pub units: Units,
    /// Paint every vertex this sRGB colour, "R,G,B" (0-255); otherwise the mesh's own colours or grey.
    #[arg(long, value_parser = parse_colour)]
    pub colour: Option<[u8; 3]>,
    /// Axis "X,Y,Z" (object frame) of a continuous rotational symmetry through the origin, e.g. 0,0,1 for a bowl.
    #[arg(long, value_parser = parse_axis)]
    pub symmetry_axis: Option<Vector3<f64>>,
    /// Search the mesh for its geometric symmetries and record them: turns about its principal and frame axes
    /// through its surface centroid that move no surface point farther than this fraction of the diameter from
    /// the surface (e.g. 0.01). Texture is not seen: a can whose label tells its turns apart is still found
    /// symmetric, so pass this only for objects that look the same.
    #[arg(long, value_name = "FRACTION")]
    pub find_symmetries: Option<f64>,
    /// Also search for the symmetries of the shape alone, within this many millimetres, and record them in
    /// models_info_shape.json beside models_info.json: the turns a render of the one-coloured mesh cannot tell
    /// apart (a box's half turns, a labelled can's), for training targets and `poseflow eval --symmetries shape`.
    /// 8 mm is about the depth camera's quantisation step at 1.6 m.
    #[arg(long, value_name = "MM")]
    pub shape_symmetries: Option<f64>,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Units {
    M,
    Mm,
}

fn three<T: std::str::FromStr>(text: &str, what: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let values: Option<Vec<T>> = parts.iter().map(|p| p.parse().ok()).collect();
    match values.and_then(|v| <[T; 3]>::try_from(v).ok()) {
        Some(v) => Ok(v),
        None => Err(format!("{text:?}: expected {what}")),
    }
}

fn parse_colour(text: &str) -> Result<[u8; 3], String> {
    three(text, "three integers 0-255 separated by commas, e.g. 200,30,30")
}

pub(crate) fn parse_axis(text: &str) -> Result<Vector3<f64>, String> {
    three::<f64>(text, "three numbers separated by commas, e.g. 0,0,1").map(Vector3::from)
}

pub fn run(args: &ImportModelArgs) -> anyhow::Result<()> {
    if args.obj_id == 0 {
        bail!("--obj-id 0: BOP object ids start at 1");
    }
    let spec = ImportSpec {
        mesh: args.mesh.clone(),
        scale: match args.units {
            Units::M => 1.0,
            Units::Mm => 1e-3,
        },
        obj_id: args.obj_id,
        colour: args.colour,
        symmetry_axis: args.symmetry_axis,
        find_symmetries: args.find_symmetries,
        shape_symmetries_mm: args.shape_symmetries,
    };
    let imported = import_model(&spec, &args.models)?;
    println!(
        "{}: {} vertices, {} triangles, diameter {:.1} mm, size {:.1} x {:.1} x {:.1} mm",
        imported.model_path.display(),
        imported.vertices,
        imported.triangles,
        imported.diameter * 1e3,
        imported.size.x * 1e3,
        imported.size.y * 1e3,
        imported.size.z * 1e3,
    );
    for symmetry in &imported.symmetries {
        println!("  symmetry: {}", describe(symmetry));
    }
    if let Some(shape) = &imported.shape_symmetries {
        println!("  shape symmetries ({}): {}", poseflow_scene::import::SHAPE_SYMMETRIES_FILE, shape.len());
        for symmetry in shape {
            println!("    {}", describe(symmetry));
        }
    }
    Ok(())
}

fn describe(symmetry: &Symmetry) -> String {
    match symmetry {
        Symmetry::Continuous { axis, offset } => format!(
            "any turn about ({:.3}, {:.3}, {:.3}) through ({:.1}, {:.1}, {:.1}) mm",
            axis.x,
            axis.y,
            axis.z,
            offset.x * 1e3,
            offset.y * 1e3,
            offset.z * 1e3
        ),
        Symmetry::Discrete(pose) => {
            let (axis, angle) = turn(&pose.rotation).map_or((Vector3::z(), 0.0), |(a, t)| (a.into_inner(), t));
            format!(
                "{:.0}° about ({:.3}, {:.3}, {:.3}), then ({:.1}, {:.1}, {:.1}) mm",
                angle.to_degrees(),
                axis.x,
                axis.y,
                axis.z,
                pose.translation.x * 1e3,
                pose.translation.y * 1e3,
                pose.translation.z * 1e3
            )
        }
    }
}
