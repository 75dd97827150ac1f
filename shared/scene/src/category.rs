//! Procedural shapes of the everyday categories (mug, bowl, bottle, can):
//! seeded generators of distinct instances for category-level training,
//! written out as BOP models so the renderer, eval and selection use them
//! as they use any other object.
//!
//! Canonical frame (the NOCS convention of category-level pose): metres,
//! **y up the symmetry axis**, the mug's handle towards **+x**, the
//! bounding box centred on the origin. The box's extents are the object's
//! size, and its diagonal the NOCS scale ([`Generated::nocs_scale`]).
//!
//! Every body is a closed profile revolved about y (thin-walled for the
//! open mug and bowl, solid for the capped bottle and can); the mug's
//! handle is a tube swept along a half-ellipse in the x–y plane whose ends
//! sit inside the wall. Parameter ranges are in [`ShapeParams::sample`]
//! and on docs/categories.md.

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use poseflow_geometry::Pose;
use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::ObjectMesh;

/// Segments around the axis of every revolved body.
const SEGMENTS: usize = 48;
/// Segments along the handle's curve, and around its tube.
const HANDLE_STEPS: usize = 24;
const TUBE_SEGMENTS: usize = 12;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    Mug,
    Bowl,
    Bottle,
    Can,
}

impl Category {
    pub const ALL: [Category; 4] = [Category::Mug, Category::Bowl, Category::Bottle, Category::Can];

    pub fn name(self) -> &'static str {
        match self {
            Category::Mug => "mug",
            Category::Bowl => "bowl",
            Category::Bottle => "bottle",
            Category::Can => "can",
        }
    }

    /// REAL275's (NOCS) class id: the code a category-level model and its
    /// messages know the category by.
    pub fn code(self) -> u32 {
        match self {
            Category::Bottle => 1,
            Category::Bowl => 2,
            Category::Can => 4,
            Category::Mug => 6,
        }
    }

    /// The category of a REAL275 class id; None for one without a
    /// generator (3 camera, 5 laptop) or none at all.
    pub fn from_code(code: u32) -> Option<Self> {
        Category::ALL.into_iter().find(|c| c.code() == code)
    }

    /// Whether every turn about the y axis leaves the shape (and its
    /// colours) unchanged: all but the mug, whose handle breaks it.
    pub fn symmetric_about_y(self) -> bool {
        self != Category::Mug
    }
}

impl std::str::FromStr for Category {
    type Err = String;
    fn from_str(text: &str) -> Result<Self, String> {
        Category::ALL
            .into_iter()
            .find(|c| c.name() == text)
            .ok_or_else(|| format!("{text:?}: expected one of mug, bowl, bottle, can"))
    }
}

/// The drawn parameters of one instance, metres; recorded beside the model.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "category", rename_all = "snake_case")]
pub enum ShapeParams {
    Mug {
        height: f32,
        bottom_radius: f32,
        top_radius: f32,
        wall: f32,
        base: f32,
        /// Tube radius, the finger gap between wall and handle at its
        /// widest, and the heights of the handle's upper and lower ends.
        handle_radius: f32,
        handle_reach: f32,
        handle_top: f32,
        handle_bottom: f32,
    },
    Bowl {
        height: f32,
        rim_radius: f32,
        foot_radius: f32,
        /// Profile exponent: radius grows as (y / height)^(1 / bulge).
        bulge: f32,
        wall: f32,
    },
    Bottle {
        height: f32,
        body_radius: f32,
        /// Height where the shoulder begins, the neck's radius and length.
        shoulder: f32,
        neck_radius: f32,
        neck_length: f32,
    },
    Can {
        height: f32,
        radius: f32,
        /// Radial inset and height of the rims at top and bottom.
        rim_inset: f32,
        rim_height: f32,
    },
}

impl ShapeParams {
    /// Draws an instance of `category`. Ranges follow real objects: mugs
    /// 8–12 cm tall and 7–11.5 cm across, bowls 12–20 cm across, bottles
    /// 15–30 cm tall, cans 6–11 cm across and 1.2–3 radii tall.
    pub fn sample<R: Rng + ?Sized>(category: Category, rng: &mut R) -> Self {
        Self::drawn(category, &mut |range| rng.random_range(range))
    }

    /// The category's mean shape: every parameter at the middle of its
    /// range (the template selection scores against, scaled to a size).
    pub fn mean(category: Category) -> Self {
        Self::drawn(category, &mut |range| 0.5 * (range.start + range.end))
    }

    /// The parameters with each value taken by `draw` from its range, in a
    /// fixed order (so a seed keeps giving the same shape).
    fn drawn(category: Category, draw: &mut dyn FnMut(std::ops::Range<f32>) -> f32) -> Self {
        match category {
            Category::Mug => {
                let height = draw(0.08..0.12);
                let bottom_radius = draw(0.035..0.05);
                let top_radius = bottom_radius * draw(0.9..1.15);
                let span = height * draw(0.45..0.75);
                let middle = height * draw(0.45..0.55);
                ShapeParams::Mug {
                    height,
                    bottom_radius,
                    top_radius,
                    wall: draw(0.003..0.006),
                    base: draw(0.005..0.01),
                    handle_radius: draw(0.004..0.007),
                    handle_reach: draw(0.02..0.035),
                    handle_top: (middle + span / 2.0).min(height - 0.01),
                    handle_bottom: (middle - span / 2.0).max(0.01),
                }
            }
            Category::Bowl => {
                let rim_radius = draw(0.06..0.1);
                ShapeParams::Bowl {
                    height: rim_radius * draw(0.5..0.9),
                    rim_radius,
                    foot_radius: rim_radius * draw(0.35..0.6),
                    bulge: draw(1.5..3.0),
                    wall: draw(0.003..0.006),
                }
            }
            Category::Bottle => {
                let height = draw(0.15..0.3);
                let body_radius = draw(0.025..0.045);
                ShapeParams::Bottle {
                    height,
                    body_radius,
                    shoulder: height * draw(0.55..0.75),
                    neck_radius: body_radius * draw(0.3..0.45),
                    neck_length: height * draw(0.1..0.2),
                }
            }
            Category::Can => {
                let radius = draw(0.03..0.055);
                ShapeParams::Can {
                    height: radius * draw(1.2..3.0),
                    radius,
                    rim_inset: draw(0.002..0.004),
                    rim_height: draw(0.003..0.006),
                }
            }
        }
    }

    pub fn category(&self) -> Category {
        match self {
            ShapeParams::Mug { .. } => Category::Mug,
            ShapeParams::Bowl { .. } => Category::Bowl,
            ShapeParams::Bottle { .. } => Category::Bottle,
            ShapeParams::Can { .. } => Category::Can,
        }
    }

    /// The body's profile, `(radius, height)` from the axis at the bottom
    /// round to the axis again (at the top for a solid, on the inner floor
    /// for an open vessel).
    fn profile(&self) -> Vec<(f32, f32)> {
        match *self {
            ShapeParams::Mug { height, bottom_radius, top_radius, wall, base, .. } => {
                let outer = |y: f32| bottom_radius + (top_radius - bottom_radius) * y / height;
                let mut profile = vec![(0.0, 0.0)];
                for k in 0..=8 {
                    let y = height * k as f32 / 8.0;
                    profile.push((outer(y), y));
                }
                for k in (0..=8).rev() {
                    let y = base + (height - base) * k as f32 / 8.0;
                    profile.push((outer(y) - wall, y));
                }
                profile.push((0.0, base));
                profile
            }
            ShapeParams::Bowl { height, rim_radius, foot_radius, bulge, wall } => {
                let outer = |t: f32| foot_radius + (rim_radius - foot_radius) * t.powf(1.0 / bulge);
                let mut profile = vec![(0.0, 0.0)];
                for k in 0..=12 {
                    let t = k as f32 / 12.0;
                    profile.push((outer(t), height * t));
                }
                for k in (0..=12).rev() {
                    let t = k as f32 / 12.0;
                    let y = wall + (height - wall) * t;
                    profile.push(((outer(t) - wall).max(0.5 * foot_radius), y));
                }
                profile.push((0.0, wall));
                profile
            }
            ShapeParams::Bottle { height, body_radius, shoulder, neck_radius, neck_length } => {
                let neck_start = height - neck_length;
                let cap = neck_radius * 1.15;
                let mut profile =
                    vec![(0.0, 0.0), (body_radius * 0.92, 0.0), (body_radius, 0.008), (body_radius, shoulder)];
                // A cosine shoulder from the body to the neck.
                for k in 1..=8 {
                    let t = k as f32 / 8.0;
                    let blend = 0.5 - 0.5 * (std::f32::consts::PI * t).cos();
                    profile.push((
                        body_radius + (neck_radius - body_radius) * blend,
                        shoulder + (neck_start - shoulder) * t,
                    ));
                }
                let cap_start = height - 0.6 * neck_length;
                profile.extend([(neck_radius, cap_start), (cap, cap_start), (cap, height), (0.0, height)]);
                profile
            }
            ShapeParams::Can { height, radius, rim_inset, rim_height } => vec![
                (0.0, 0.0),
                (radius - rim_inset, 0.0),
                (radius, rim_height),
                (radius, height - rim_height),
                (radius - rim_inset, height),
                (0.0, height),
            ],
        }
    }
}

/// One generated instance in its canonical frame.
#[derive(Debug, Clone)]
pub struct Generated {
    pub params: ShapeParams,
    pub mesh: ObjectMesh,
    /// Bounding-box extents (x, y, z), metres.
    pub size: Vector3<f32>,
}

impl Generated {
    pub fn category(&self) -> Category {
        self.params.category()
    }

    /// The bounding box's diagonal: NOCS divides by it.
    pub fn nocs_scale(&self) -> f32 {
        self.size.norm()
    }
}

/// The instance of `category` drawn from `seed`: the same seed, the same
/// shape and colours.
pub fn generate(category: Category, seed: u64) -> Generated {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ ((category as u64) << 56));
    let params = ShapeParams::sample(category, &mut rng);
    let body_colour: [u8; 3] = std::array::from_fn(|_| rng.random_range(30..230));
    let label_colour: [u8; 3] = std::array::from_fn(|_| rng.random_range(30..230));
    build(params, body_colour, label_colour)
}

/// The category's mean shape ([`ShapeParams::mean`]), grey.
pub fn mean_shape(category: Category) -> Generated {
    build(ShapeParams::mean(category), [128; 3], [128; 3])
}

/// The category's mean shape stretched along each canonical axis so that
/// its bounding box has extents `size` (metres): the template a
/// category-level estimate is scored against when the instance's own mesh
/// is unknown.
pub fn template(category: Category, size: Vector3<f32>) -> ObjectMesh {
    let mean = mean_shape(category);
    let stretch = size.component_div(&mean.size);
    let mut mesh = mean.mesh;
    for v in &mut mesh.vertices {
        v.coords.component_mul_assign(&stretch);
    }
    mesh.normals = None;
    mesh
}

/// The mesh of `params` in the canonical frame, coloured.
fn build(params: ShapeParams, body_colour: [u8; 3], label_colour: [u8; 3]) -> Generated {
    let mut mesh = revolve(&params.profile(), SEGMENTS);
    let (low, high) = match params {
        // A printed label round the middle of cans and bottles: colour
        // varies with height only, so the turns about y stay symmetric.
        ShapeParams::Bottle { shoulder, .. } => (0.25 * shoulder, 0.85 * shoulder),
        ShapeParams::Can { height, .. } => (0.15 * height, 0.85 * height),
        _ => (f32::INFINITY, f32::INFINITY),
    };
    mesh.colors = Some(
        mesh.vertices.iter().map(|v| if (low..=high).contains(&v.y) { label_colour } else { body_colour }).collect(),
    );
    if let ShapeParams::Mug {
        height,
        bottom_radius,
        top_radius,
        wall,
        handle_radius,
        handle_reach,
        handle_top,
        handle_bottom,
        ..
    } = params
    {
        let outer = |y: f32| bottom_radius + (top_radius - bottom_radius) * y / height;
        // The ends are capped in the middle of the wall, so the handle
        // meets it without a gap.
        let start = outer(handle_top) - 0.5 * wall;
        let end = outer(handle_bottom) - 0.5 * wall;
        let mut handle = swept_handle(start, end, handle_top, handle_bottom, handle_reach, handle_radius);
        handle.colors = Some(vec![body_colour; handle.vertices.len()]);
        append(&mut mesh, handle);
    }
    let (min, max) = mesh.bounds();
    let centre = (min.coords + max.coords) / 2.0;
    for v in &mut mesh.vertices {
        *v -= centre;
    }
    mesh.normals = Some(vertex_normals(&mesh));
    Generated { params, mesh, size: max - min }
}

/// `P(r, y, θ) = (r cos θ, y, r sin θ)`. The triangles' winding makes
/// their normals point out of the solid the profile encloses (for a
/// profile running outwards along the bottom, then up): the profile's
/// tangent × the turn's tangent. Profile points on the axis become one
/// vertex (a pole) instead of a ring.
fn revolve(profile: &[(f32, f32)], segments: usize) -> ObjectMesh {
    let mut vertices = Vec::new();
    // Per profile point: its first vertex and whether it is a pole.
    let mut rings = Vec::with_capacity(profile.len());
    for &(r, y) in profile {
        let first = vertices.len() as u32;
        if r <= 0.0 {
            vertices.push(Point3::new(0.0, y, 0.0));
            rings.push((first, true));
        } else {
            for j in 0..segments {
                let theta = std::f32::consts::TAU * j as f32 / segments as f32;
                vertices.push(Point3::new(r * theta.cos(), y, r * theta.sin()));
            }
            rings.push((first, false));
        }
    }
    let at = |(first, pole): (u32, bool), j: usize| if pole { first } else { first + (j % segments) as u32 };
    let mut triangles = Vec::new();
    for pair in rings.windows(2) {
        let (this, next) = (pair[0], pair[1]);
        for j in 0..segments {
            let (a, b, c, d) = (at(this, j), at(next, j), at(this, j + 1), at(next, j + 1));
            if !this.1 {
                triangles.push([a, b, c]);
            }
            if !next.1 {
                triangles.push([b, d, c]);
            }
        }
    }
    ObjectMesh { vertices, triangles, normals: None, colors: None }
}

/// A closed tube of radius `tube` along a half-ellipse in the x–y plane:
/// from `(x_top, y_top)` out to `reach` beyond the wall and back to
/// `(x_bottom, y_bottom)`, with flat caps at both ends.
fn swept_handle(x_top: f32, x_bottom: f32, y_top: f32, y_bottom: f32, reach: f32, tube: f32) -> ObjectMesh {
    let (middle, half_span) = ((y_top + y_bottom) / 2.0, (y_top - y_bottom) / 2.0);
    let curve = |phi: f32| {
        let base = x_top + (x_bottom - x_top) * phi / std::f32::consts::PI;
        Point3::new(base + (reach + tube) * phi.sin(), middle + half_span * phi.cos(), 0.0)
    };
    let mut vertices = Vec::new();
    let mut centres = Vec::new();
    for i in 0..=HANDLE_STEPS {
        let phi = std::f32::consts::PI * i as f32 / HANDLE_STEPS as f32;
        let h = 1e-3;
        let tangent = (curve((phi + h).min(std::f32::consts::PI)) - curve((phi - h).max(0.0))).normalize();
        let side = Vector3::z();
        let normal = tangent.cross(&side);
        let centre = curve(phi);
        centres.push(centre);
        for j in 0..TUBE_SEGMENTS {
            let psi = std::f32::consts::TAU * j as f32 / TUBE_SEGMENTS as f32;
            vertices.push(centre + tube * (psi.cos() * normal + psi.sin() * side));
        }
    }
    let ring = |i: usize, j: usize| (i * TUBE_SEGMENTS + j % TUBE_SEGMENTS) as u32;
    let mut triangles = Vec::new();
    for i in 0..HANDLE_STEPS {
        for j in 0..TUBE_SEGMENTS {
            triangles.push([ring(i, j), ring(i, j + 1), ring(i + 1, j)]);
            triangles.push([ring(i + 1, j), ring(i, j + 1), ring(i + 1, j + 1)]);
        }
    }
    // Caps: each uses its rim's edges the other way round from the sides.
    let (first, last) = (vertices.len() as u32, vertices.len() as u32 + 1);
    vertices.extend([centres[0], centres[HANDLE_STEPS]]);
    for j in 0..TUBE_SEGMENTS {
        triangles.push([first, ring(0, j + 1), ring(0, j)]);
        triangles.push([last, ring(HANDLE_STEPS, j), ring(HANDLE_STEPS, j + 1)]);
    }
    let mut handle = ObjectMesh { vertices, triangles, normals: None, colors: None };
    // Consistent, but which way round depends on the curve's direction: a
    // closed part whose volume comes out negative is wound inwards.
    if handle.enclosed_volume() < 0.0 {
        handle.triangles.iter_mut().for_each(|t| t.swap(1, 2));
    }
    handle
}

fn append(mesh: &mut ObjectMesh, part: ObjectMesh) {
    let offset = mesh.vertices.len() as u32;
    mesh.vertices.extend(part.vertices);
    mesh.triangles.extend(part.triangles.into_iter().map(|t| t.map(|i| i + offset)));
    if let (Some(colours), Some(more)) = (&mut mesh.colors, part.colors) {
        colours.extend(more);
    }
}

/// Area-weighted normals of the triangles at each vertex.
fn vertex_normals(mesh: &ObjectMesh) -> Vec<Vector3<f32>> {
    let mut normals = vec![Vector3::zeros(); mesh.vertices.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let n = (b - a).cross(&(c - a));
        for &i in t {
            normals[i as usize] += n;
        }
    }
    normals.into_iter().map(|n| n.try_normalize(1e-12).unwrap_or_else(Vector3::y)).collect()
}

/// The seed of the `index`-th instance drawn with `seed`: distinct for
/// every pair, so runs with different seeds share no shape.
pub fn instance_seed(seed: u64, index: u64) -> u64 {
    // SplitMix64's finaliser over the pair.
    let mut z = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(index).wrapping_add(0x6A09_E667_F3BC_C909);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One object written by [`write_instances`].
#[derive(Debug, Clone)]
pub struct WrittenInstance {
    pub obj_id: u32,
    pub seed: u64,
    pub generated: Generated,
    pub model: crate::import::Imported,
}

/// The file beside `models_info.json` that names each generated object's
/// category, seed, size and parameters.
pub const CATEGORIES_FILE: &str = "categories.json";

/// One object's entry in [`CATEGORIES_FILE`], as the evaluation reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct CategoryEntry {
    pub category: Category,
    /// Bounding-box extents along canonical x, y, z, metres.
    pub size: Vector3<f64>,
    /// A mug's handle: the canonical x beyond which a surface point is
    /// handle, not body (metres); None for the other categories, or a mug
    /// whose file gives neither its shape parameters nor `handle_beyond_x_mm`.
    pub handle_beyond_x: Option<f64>,
    /// Takes the object's model-frame points to its canonical frame:
    /// identity for a generated instance, which is made in that frame; a
    /// scanned mesh (a YCB mug) keeps its own model frame, so that the
    /// dataset's poses stay valid, and [`annotate`] records this instead.
    pub canonical_from_model: Pose,
}

/// Where an object's canonical category frame lies in its model frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CanonicalFrame {
    /// Model-frame points (metres) to canonical-frame points.
    pub canonical_from_model: Pose,
    /// Extents of the canonical bounding box, metres.
    pub size: Vector3<f64>,
}

/// The canonical frame of a mesh that was not made in it: canonical y
/// along `up` (the model-frame direction from the object's base to its
/// top), canonical x along `front` made perpendicular to `up` (a mug's
/// handle; any direction across the axis for the other categories, where
/// the turn about y is not scored), and the canonical box centred on the
/// origin.
pub fn canonical_frame(
    mesh: &ObjectMesh,
    up: &Vector3<f64>,
    front: &Vector3<f64>,
) -> Result<CanonicalFrame, crate::SceneError> {
    let y = up
        .try_normalize(1e-9)
        .ok_or_else(|| crate::SceneError::Invalid(format!("up {up:?}: expected a non-zero direction")))?;
    let across = front - y * front.dot(&y);
    // A front within ~6° of the axis leaves its perpendicular part to noise.
    let x = across.try_normalize(0.1 * front.norm()).ok_or_else(|| {
        crate::SceneError::Invalid(format!("front {front:?}: expected a direction across up {up:?}, not along it"))
    })?;
    let z = x.cross(&y);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
    let turned: Vec<Vector3<f64>> = mesh.vertices.iter().map(|v| rotation * v.coords.cast::<f64>()).collect();
    let min = turned.iter().fold(Vector3::repeat(f64::INFINITY), |m, v| m.inf(v));
    let max = turned.iter().fold(Vector3::repeat(f64::NEG_INFINITY), |m, v| m.sup(v));
    if turned.is_empty() {
        return Err(crate::SceneError::Invalid("a mesh without vertices has no canonical frame".into()));
    }
    Ok(CanonicalFrame { canonical_from_model: Pose::new(rotation, -(min + max) / 2.0), size: max - min })
}

/// The model axis most across `up`: a front for the categories whose turn
/// about their axis is not scored.
pub fn any_front(up: &Vector3<f64>) -> Vector3<f64> {
    let axes = [Vector3::x(), Vector3::y(), Vector3::z()];
    axes.into_iter().min_by(|a, b| a.dot(up).abs().total_cmp(&b.dot(up).abs())).expect("three axes")
}

/// Records object `obj_id` of `models_dir` as one of `category` in
/// [`CATEGORIES_FILE`], with its canonical frame and size; other entries
/// are kept. A mug's handle is taken to begin past its body, whose
/// diameter is the canonical box's z extent (the handle only widens x).
pub fn annotate(
    models_dir: &std::path::Path,
    obj_id: u32,
    category: Category,
    frame: &CanonicalFrame,
) -> Result<CategoryEntry, crate::SceneError> {
    let table_path = models_dir.join(CATEGORIES_FILE);
    let mut table: serde_json::Map<String, serde_json::Value> =
        if table_path.exists() { crate::bop::read_json(&table_path)? } else { serde_json::Map::new() };
    let handle_beyond_x = (category == Category::Mug).then(|| -frame.size.x / 2.0 + frame.size.z + 0.001);
    let rotation = frame.canonical_from_model.rotation.matrix();
    let mut entry = serde_json::json!({
        "category": category.name(),
        "size_mm": (frame.size * 1e3).as_slice(),
        "canonical_from_model": {
            "rotation": (0..9).map(|i| rotation[(i / 3, i % 3)]).collect::<Vec<f64>>(),
            "translation_mm": (frame.canonical_from_model.translation * 1e3).as_slice(),
        },
    });
    if let Some(beyond_x) = handle_beyond_x {
        entry["handle_beyond_x_mm"] = serde_json::json!(beyond_x * 1e3);
    }
    table.insert(obj_id.to_string(), entry);
    crate::bop::write_json(&table_path, &table)?;
    Ok(CategoryEntry { category, size: frame.size, handle_beyond_x, canonical_from_model: frame.canonical_from_model })
}

/// An entry's `canonical_from_model`: `rotation` nine values row-major,
/// `translation_mm` three; identity when absent.
fn read_canonical_from_model(entry: &serde_json::Value) -> Result<Pose, String> {
    let Some(frame) = entry.get("canonical_from_model") else { return Ok(Pose::identity()) };
    let rotation: [f64; 9] = frame
        .get("rotation")
        .and_then(|r| serde_json::from_value(r.clone()).ok())
        .ok_or("\"canonical_from_model.rotation\" must be nine numbers, row-major")?;
    let translation: [f64; 3] = frame
        .get("translation_mm")
        .and_then(|t| serde_json::from_value(t.clone()).ok())
        .filter(|t: &[f64; 3]| t.iter().all(|v| v.is_finite()))
        .ok_or("\"canonical_from_model.translation_mm\" must be three finite numbers (millimetres)")?;
    let rotation = poseflow_geometry::pose::project_to_rotation(
        &Matrix3::from_row_slice(&rotation),
        "canonical_from_model.rotation",
        1e-6,
    )
    .map_err(|e| e.to_string())?;
    Ok(Pose::new(rotation, Vector3::from(translation) / 1e3))
}

/// Reads `<models_dir>/categories.json`: per object id its category, size
/// and, for a mug, where its handle begins. Errors name the file, the
/// object and the field.
pub fn read_categories(models_dir: &std::path::Path) -> Result<BTreeMap<u32, CategoryEntry>, crate::SceneError> {
    let path = models_dir.join(CATEGORIES_FILE);
    let table: serde_json::Map<String, serde_json::Value> = crate::bop::read_json(&path)?;
    let bad = |detail: String| crate::SceneError::Invalid(format!("{}: {detail}", path.display()));
    let mut entries = BTreeMap::new();
    for (key, entry) in &table {
        let obj_id: u32 = key.parse().map_err(|_| bad(format!("key {key:?}: expected an object id")))?;
        let category: Category = entry
            .get("category")
            .and_then(|c| c.as_str())
            .ok_or_else(|| bad(format!("object {obj_id}: no \"category\"")))?
            .parse()
            .map_err(|e: String| bad(format!("object {obj_id}: category {e}")))?;
        let size_mm: [f64; 3] = entry
            .get("size_mm")
            .and_then(|s| serde_json::from_value(s.clone()).ok())
            .filter(|s: &[f64; 3]| s.iter().all(|v| v.is_finite() && *v > 0.0))
            .ok_or_else(|| bad(format!("object {obj_id}: \"size_mm\" must be three extents > 0 (millimetres)")))?;
        let size = Vector3::from(size_mm) / 1e3;
        let explicit = entry.get("handle_beyond_x_mm").and_then(|v| v.as_f64()).map(|mm| mm / 1e3);
        let handle_beyond_x = match category {
            Category::Mug => explicit.or_else(|| mug_handle_start(entry.get("params_m")?, size.x)),
            _ => None,
        };
        let canonical_from_model =
            read_canonical_from_model(entry).map_err(|detail| bad(format!("object {obj_id}: {detail}")))?;
        entries.insert(obj_id, CategoryEntry { category, size, handle_beyond_x, canonical_from_model });
    }
    Ok(entries)
}

/// Where a generated mug's handle begins along canonical x: the body's
/// axis lies one outer radius in from the box's −x side, and the handle
/// starts past the body's outer wall on +x (a millimetre of margin).
fn mug_handle_start(params: &serde_json::Value, size_x: f64) -> Option<f64> {
    let radius = |key: &str| params.get(key).and_then(|v| v.as_f64());
    let outer = radius("bottom_radius")?.max(radius("top_radius")?);
    Some(-size_x / 2.0 + 2.0 * outer + 0.001)
}

/// Writes `count` instances of each of `categories` into `models_dir` as
/// BOP models with ids from `first_id` (categories in turn), recording
/// each in [`CATEGORIES_FILE`]. Other objects of the directory are kept;
/// the same ids are replaced.
pub fn write_instances(
    categories: &[Category],
    count: u32,
    seed: u64,
    first_id: u32,
    models_dir: &std::path::Path,
) -> Result<Vec<WrittenInstance>, crate::SceneError> {
    use crate::symmetry::Symmetry;
    if first_id == 0 {
        return Err(crate::SceneError::Invalid("first object id 0: BOP object ids start at 1".into()));
    }
    let total = u64::from(count) * categories.len() as u64;
    if u64::from(first_id) + total > u64::from(u32::MAX) {
        return Err(crate::SceneError::Invalid(format!("{total} objects from id {first_id}: ids past {}", u32::MAX)));
    }
    let table_path = models_dir.join(CATEGORIES_FILE);
    let mut table: serde_json::Map<String, serde_json::Value> =
        if table_path.exists() { crate::bop::read_json(&table_path)? } else { serde_json::Map::new() };
    let mut written = Vec::new();
    let mut obj_id = first_id;
    for &category in categories {
        for i in 0..count {
            // Keyed by the category itself, not its place in the list: the
            // cans of `--categories can` are the cans of a run of all four.
            let instance = instance_seed(seed, (category as u64) << 32 | u64::from(i));
            let generated = generate(category, instance);
            let symmetries = if category.symmetric_about_y() {
                vec![Symmetry::Continuous { axis: Vector3::y_axis(), offset: Vector3::zeros() }]
            } else {
                Vec::new()
            };
            let model = crate::import::write_model(&generated.mesh, obj_id, symmetries, models_dir)?;
            let mm = |v: f32| f64::from(v) * 1e3;
            table.insert(
                obj_id.to_string(),
                serde_json::json!({
                    "category": category.name(),
                    "seed": instance,
                    "size_mm": [mm(generated.size.x), mm(generated.size.y), mm(generated.size.z)],
                    "nocs_scale_mm": mm(generated.nocs_scale()),
                    "params_m": generated.params,
                }),
            );
            written.push(WrittenInstance { obj_id, seed: instance, generated, model });
            obj_id += 1;
        }
    }
    crate::bop::write_json(&table_path, &table)?;
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::HashMap;

    /// Each undirected edge of a closed, consistently wound surface is
    /// used once in each direction.
    fn is_closed_and_consistent(mesh: &ObjectMesh) -> bool {
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &mesh.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        directed.iter().all(|(&(a, b), &n)| n == 1 && directed.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn categories_read_back_with_sizes_and_where_a_mug_handle_begins() {
        let dir = std::env::temp_dir().join(format!("poseflow-categories-read-{}", std::process::id()));
        let written = write_instances(&[Category::Mug, Category::Can], 2, 5, 1, &dir).unwrap();
        let read = read_categories(&dir).unwrap();
        assert_eq!(read.len(), 4);
        for w in &written {
            let entry = &read[&w.obj_id];
            assert_eq!(entry.category, w.generated.category());
            assert!((entry.size - w.generated.size.cast::<f64>()).abs().max() < 1e-6);
            match w.generated.params {
                ShapeParams::Mug { .. } => {
                    // The handle reaches past the start, which lies past the body.
                    let start = entry.handle_beyond_x.unwrap() as f32;
                    let beyond = w.generated.mesh.vertices.iter().filter(|v| v.x > start).count();
                    assert!(beyond > 0, "some of the handle");
                    let (min, _) = w.generated.mesh.bounds();
                    assert!(start - min.x > 0.07, "past the body: {}", start - min.x);
                }
                _ => assert_eq!(entry.handle_beyond_x, None),
            }
        }
        // A bad entry is named.
        std::fs::write(dir.join(CATEGORIES_FILE), r#"{"3": {"category": "mug", "size_mm": [0, 1, 2]}}"#).unwrap();
        let error = read_categories(&dir).unwrap_err().to_string();
        assert!(error.contains("object 3") && error.contains("size_mm"), "{error}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn codes_are_real275_class_ids() {
        let codes: Vec<(u32, &str)> = Category::ALL.iter().map(|c| (c.code(), c.name())).collect();
        assert_eq!(codes, [(6, "mug"), (2, "bowl"), (1, "bottle"), (4, "can")]);
        for category in Category::ALL {
            assert_eq!(Category::from_code(category.code()), Some(category));
        }
        assert_eq!(Category::from_code(3), None);
        assert_eq!(Category::from_code(0), None);
    }

    #[test]
    fn a_template_has_the_asked_extents_and_stays_centred() {
        for category in Category::ALL {
            let size = Vector3::new(0.07, 0.21, 0.05);
            let mesh = template(category, size);
            let (min, max) = mesh.bounds();
            assert!((max - min - size).abs().max() < 1e-6, "{category:?}: {:?}", max - min);
            assert!((max.coords + min.coords).abs().max() < 1e-6, "{category:?}");
        }
        // The mean shape's parameters are each range's midpoint.
        let ShapeParams::Can { radius, height, .. } = ShapeParams::mean(Category::Can) else { panic!("a can") };
        assert!((radius - 0.0425).abs() < 1e-6 && (height - 0.0425 * 2.1).abs() < 1e-6);
    }

    #[test]
    fn a_can_is_a_cylinder_with_its_rims() {
        // Radius 4 cm, height 10 cm, rims 3 mm in over 5 mm: extents 8 × 10
        // × 8 cm, and the volume of the cylinder less the two rims' rings
        // (a ring of triangular section, π·r·inset·rim_height each, to first
        // order), less what 48 flat sides cut off a circle.
        let params = ShapeParams::Can { height: 0.1, radius: 0.04, rim_inset: 0.003, rim_height: 0.005 };
        let mesh = revolve(&params.profile(), SEGMENTS);
        assert!(is_closed_and_consistent(&mesh));
        let (min, max) = mesh.bounds();
        assert!(((max - min) - Vector3::new(0.08, 0.1, 0.08)).norm() < 1e-6, "{:?}", max - min);
        let polygon = 0.5 * SEGMENTS as f64 * (std::f64::consts::TAU / SEGMENTS as f64).sin();
        let rims = 2.0 * std::f64::consts::PI * 0.04 * 0.003 * 0.005;
        let expected = polygon * 0.04f64.powi(2) * 0.1 - rims;
        let volume = mesh.enclosed_volume();
        assert!((volume - expected).abs() < 0.02 * expected, "volume {volume} against {expected}");
    }

    #[test]
    fn the_mug_is_centred_with_its_handle_towards_plus_x() {
        for seed in 0..20 {
            let mug = generate(Category::Mug, seed);
            let (min, max) = mug.mesh.bounds();
            assert!((min.coords + max.coords).norm() < 1e-5, "centred: {min:?} {max:?}");
            let ShapeParams::Mug { height, handle_top, handle_reach, .. } = mug.params else { panic!() };
            assert!((mug.size.y - height).abs() < 1e-5, "y is the axis");
            // At the rim (above the handle) only the body is there: it
            // reaches −x as far as anything, and +x short of the handle.
            assert!(handle_top < height);
            let rim: Vec<_> = mug.mesh.vertices.iter().filter(|v| v.y > max.y - 1e-4).collect();
            let rim_max = rim.iter().map(|v| v.x).fold(f32::MIN, f32::max);
            let rim_min = rim.iter().map(|v| v.x).fold(f32::MAX, f32::min);
            assert!(rim_max + handle_reach < max.x, "seed {seed}: handle towards +x ({rim_max} vs {})", max.x);
            assert!((rim_min - min.x).abs() < 0.01, "seed {seed}: the body on −x");
            assert!((max.z + min.z).abs() < 1e-4, "seed {seed}: nothing sticks out along z");
        }
    }

    #[test]
    fn the_handle_is_one_closed_outward_tube() {
        let handle = swept_handle(0.04, 0.045, 0.08, 0.03, 0.025, 0.005);
        assert!(is_closed_and_consistent(&handle));
        // Close to π r² times the centreline's length (half an ellipse).
        let volume = handle.enclosed_volume();
        assert!(volume > 0.0);
        let (a, b): (f64, f64) = (0.025 + 0.005, 0.025);
        let half_ellipse = std::f64::consts::PI * (3.0 * (a + b) - ((3.0 * a + b) * (a + 3.0 * b)).sqrt()) / 2.0;
        let expected = std::f64::consts::PI * 0.005f64.powi(2) * half_ellipse;
        assert!((volume - expected).abs() < 0.1 * expected, "{volume} against {expected}");
    }

    #[test]
    fn instances_are_written_as_bop_models_with_their_categories() {
        let dir = std::env::temp_dir().join(format!("poseflow-categories-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let written = write_instances(&[Category::Mug, Category::Can], 2, 5, 101, &dir).unwrap();
        assert_eq!(written.iter().map(|w| w.obj_id).collect::<Vec<_>>(), [101, 102, 103, 104]);
        let info = poseflow_geometry::models_info::ModelsInfo::from_path(&dir.join("models_info.json")).unwrap();
        assert!(!info.objects[&101].is_symmetric(), "a mug has no symmetry of its own");
        let can = &info.objects[&103];
        assert_eq!(can.symmetries_continuous.len(), 1);
        assert!((can.symmetries_continuous[0].axis.into_inner() - Vector3::y()).norm() < 1e-12);
        let size = can.size.unwrap();
        assert!((size - written[2].generated.size.cast::<f64>()).norm() < 1e-6, "{size:?} metres in models_info");
        let table: serde_json::Value = crate::bop::read_json(&dir.join(CATEGORIES_FILE)).unwrap();
        assert_eq!(table["102"]["category"], "mug");
        assert_eq!(table["104"]["params_m"]["category"], "can");
        assert_eq!(table["104"]["seed"], written[3].seed);
        // The model reads back with the generated vertices (millimetres in
        // the file).
        let mesh = crate::load_mesh(&dir.join(crate::model_file_name(104)), 1e-3).unwrap();
        assert_eq!(mesh.vertices.len(), written[3].generated.mesh.vertices.len());
        assert!((mesh.vertices[5] - written[3].generated.mesh.vertices[5]).norm() < 1e-6);
        // A category's instances do not depend on the others asked for.
        let cans = write_instances(&[Category::Can], 2, 5, 201, &dir).unwrap();
        assert_eq!(cans[1].seed, written[3].seed);
        assert_eq!(cans[1].generated.mesh.vertices, written[3].generated.mesh.vertices);
        // Different instances, different shapes; a zero id is refused.
        assert_ne!(written[0].generated.params, written[1].generated.params);
        assert!(write_instances(&[Category::Bowl], 1, 5, 0, &dir).unwrap_err().to_string().contains("start at 1"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn names_parse_back_and_others_are_refused() {
        for category in Category::ALL {
            assert_eq!(category.name().parse::<Category>(), Ok(category));
        }
        assert!("cup".parse::<Category>().unwrap_err().contains("mug, bowl, bottle, can"));
    }

    /// `mesh` moved into a model frame by `model_from_canonical`.
    fn moved(mesh: &ObjectMesh, model_from_canonical: &Pose) -> ObjectMesh {
        let mut moved = mesh.clone();
        for v in &mut moved.vertices {
            *v = model_from_canonical.transform_point(&v.cast::<f64>()).cast::<f32>();
        }
        moved
    }

    #[test]
    fn an_annotated_mug_reads_back_with_its_frame_and_where_its_handle_begins() {
        // The generated mug as a scan would have it: z up, handle along +x,
        // its origin off the box centre.
        let mug = generate(Category::Mug, 3);
        let model_from_canonical = Pose::new(
            Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2),
            Vector3::new(0.004, -0.002, 0.01),
        );
        let scan = moved(&mug.mesh, &model_from_canonical);
        let frame = canonical_frame(&scan, &Vector3::z(), &Vector3::x()).unwrap();
        let dir = std::env::temp_dir().join(format!("poseflow-annotate-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        annotate(&dir, 7, Category::Mug, &frame).unwrap();
        let entry = &read_categories(&dir).unwrap()[&7];
        let back = entry.canonical_from_model * model_from_canonical;
        assert!((back.rotation.matrix() - Matrix3::identity()).abs().max() < 1e-9, "{back:?}");
        assert!(back.translation.norm() < 1e-6, "{back:?}");
        assert!((entry.size - mug.size.cast::<f64>()).abs().max() < 1e-6, "{:?}", entry.size);
        // The box rule puts the handle's start where the generator's own
        // parameters do.
        let from_params = mug_handle_start(&serde_json::to_value(mug.params).unwrap(), entry.size.x).unwrap();
        assert!((entry.handle_beyond_x.unwrap() - from_params).abs() < 1e-6);
        // A rotation that is not one is named.
        std::fs::write(
            dir.join(CATEGORIES_FILE),
            r#"{"7": {"category": "can", "size_mm": [1, 2, 3],
                "canonical_from_model": {"rotation": [1, 0, 0, 0, 2, 0, 0, 0, 1], "translation_mm": [0, 0, 0]}}}"#,
        )
        .unwrap();
        let error = read_categories(&dir).unwrap_err().to_string();
        assert!(error.contains("object 7") && error.contains("canonical_from_model.rotation"), "{error}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_upright_scene_stands_an_annotated_scan_on_its_base() {
        let dir = std::env::temp_dir().join(format!("poseflow-annotated-scene-{}", std::process::id()));
        let model_from_canonical =
            Pose::new(Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2), Vector3::zeros());
        let scan = moved(&generate(Category::Bottle, 4).mesh, &model_from_canonical);
        crate::import::write_model(&scan, 1, Vec::new(), &dir).unwrap();
        annotate(&dir, 1, Category::Bottle, &canonical_frame(&scan, &Vector3::z(), &Vector3::x()).unwrap()).unwrap();
        let library = crate::ModelLibrary::load(&dir, &[]).unwrap();
        let style = crate::scene::SceneStyle { upright: true, ..Default::default() };
        for seed in 0..5 {
            let mut rng = poseflow_geometry::sampling::seeded_rng(seed);
            let scene = crate::scene::compose_styled_scene(&library, crate::scene::Occlusion::Low, &style, &mut rng);
            let top = scene.objects[0].world_from_object.rotation * (model_from_canonical.rotation * Vector3::y());
            assert!((top - Vector3::z()).norm() < 1e-9, "the bottle's top points {top:?}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_front_along_up_or_no_up_is_refused() {
        let can = generate(Category::Can, 1).mesh;
        let along = canonical_frame(&can, &Vector3::z(), &Vector3::new(0.0, 0.01, 1.0)).unwrap_err().to_string();
        assert!(along.contains("front") && along.contains("across"), "{along}");
        let none = canonical_frame(&can, &Vector3::zeros(), &Vector3::x()).unwrap_err().to_string();
        assert!(none.contains("up"), "{none}");
        assert_eq!(any_front(&Vector3::new(0.9, 0.1, 0.0)), Vector3::z());
    }

    proptest! {
        /// Whatever rigid motion took a generated instance into its model
        /// frame, the canonical frame found from `up` and `front` (the
        /// moved y and x, with a tilt of front towards up) undoes it.
        #[test]
        fn canonical_frame_undoes_any_rigid_motion(
            seed in 0u64..1_000,
            which in 0usize..4,
            axis in proptest::array::uniform3(-1.0f64..1.0),
            angle in 0.0f64..3.1,
            shift in proptest::array::uniform3(-0.2f64..0.2),
            tilt in -0.5f64..0.5,
        ) {
            let shape = generate(Category::ALL[which], seed);
            let axis = nalgebra::Unit::try_new(Vector3::from(axis), 1e-3).unwrap_or(Vector3::z_axis());
            let motion = Pose::new(Rotation3::from_axis_angle(&axis, angle), Vector3::from(shift));
            let up = motion.rotation * Vector3::y();
            let front = motion.rotation * Vector3::x() + up * tilt;
            let frame = canonical_frame(&moved(&shape.mesh, &motion), &up, &front).unwrap();
            let back = frame.canonical_from_model * motion;
            prop_assert!((back.rotation.matrix() - Matrix3::identity()).abs().max() < 1e-9, "{:?}", back);
            prop_assert!(back.translation.norm() < 1e-5, "{:?}", back);
            prop_assert!((frame.size - shape.size.cast::<f64>()).abs().max() < 1e-5);
        }

        /// Every instance is closed and wound outwards, centred on its
        /// box, within the documented size ranges, and the same seed gives
        /// the same shape.
        #[test]
        fn generated_shapes_are_closed_centred_and_reproducible(seed in 0u64..1_000_000, which in 0usize..4) {
            let category = Category::ALL[which];
            let shape = generate(category, seed);
            let body_and_handle_volume = shape.mesh.enclosed_volume();
            prop_assert!(body_and_handle_volume > 0.0, "volume {}", body_and_handle_volume);
            let (min, max) = shape.mesh.bounds();
            prop_assert!((min.coords + max.coords).norm() < 1e-5);
            let tallest = match category {
                Category::Mug => 0.12, Category::Bowl => 0.09, Category::Bottle => 0.3, Category::Can => 0.165,
            };
            prop_assert!(shape.size.y > 0.0 && shape.size.y <= tallest + 1e-5, "height {}", shape.size.y);
            prop_assert!(shape.size.x <= 0.25 && shape.size.z <= 0.2);
            if category.symmetric_about_y() {
                prop_assert!((shape.size.x - shape.size.z).abs() < 1e-4);
            }
            let again = generate(category, seed);
            prop_assert_eq!(&again.mesh.vertices, &shape.mesh.vertices);
            prop_assert_eq!(again.params, shape.params);
        }

        /// The body alone (the handle is a second closed part) is one
        /// closed, consistently wound surface.
        #[test]
        fn revolved_bodies_are_closed(seed in 0u64..1_000_000, which in 0usize..4) {
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let params = ShapeParams::sample(Category::ALL[which], &mut rng);
            let body = revolve(&params.profile(), SEGMENTS);
            prop_assert!(is_closed_and_consistent(&body));
            prop_assert!(body.enclosed_volume() > 0.0);
        }
    }
}
