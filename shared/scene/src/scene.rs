//! Random tabletop scenes: objects resting on a support plane among clutter
//! shapes, seen from cameras on a view hemisphere.
//!
//! World frame: z up, the support plane is `z = 0`, metres. Camera poses
//! are `camera_from_world` (BOP's `cam_R_w2c`, `cam_t_w2c`); object poses
//! `world_from_object`, so `camera_from_object = camera_from_world ·
//! world_from_object` (BOP's `cam_R_m2c`, `cam_t_m2c`).

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_geometry::Pose;
use rand::Rng;

use crate::primitives::{ClutterShape, Texture, support_plane};
use crate::{Camera, Frame, Light, ModelLibrary, Placed, RenderModel, render, silhouettes, truncated_pixels};

/// How crowded a scene is: how many clutter shapes, how big, and how close
/// objects stand to each other.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Occlusion {
    Low,
    Medium,
    High,
}

struct Crowding {
    clutter_count: (u32, u32),
    /// Largest clutter size as a fraction of the median object diameter.
    clutter_size: f32,
    /// Free space kept between footprints, metres.
    gap: f32,
    /// Share of the placement disk covered by footprints.
    packing: f32,
}

impl Occlusion {
    fn crowding(self) -> Crowding {
        match self {
            Self::Low => Crowding { clutter_count: (0, 1), clutter_size: 0.6, gap: 0.03, packing: 0.15 },
            Self::Medium => Crowding { clutter_count: (2, 4), clutter_size: 0.9, gap: 0.01, packing: 0.3 },
            Self::High => Crowding { clutter_count: (5, 8), clutter_size: 1.3, gap: 0.0, packing: 0.5 },
        }
    }
}

/// One target object of a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneObject {
    pub obj_id: u32,
    /// Index into [`ModelLibrary::objects`].
    pub library_index: usize,
    pub world_from_object: Pose,
}

/// A composed scene: target objects, distractors and the table.
#[derive(Debug, Clone)]
pub struct Scene {
    pub objects: Vec<SceneObject>,
    pub clutter: Vec<(RenderModel, Pose)>,
    pub plane: RenderModel,
    /// The point cameras look at: the middle of the objects, half-way up.
    pub centre: Point3<f64>,
    /// Radius of the disk the objects stand in.
    pub spread: f64,
    /// Colour of pixels that see nothing (beyond the table).
    pub background: [u8; 3],
    /// With [`SceneStyle::textured`]: the pattern of those pixels (image
    /// space, pixels), replacing `background`.
    pub backdrop: Option<Texture>,
}

/// What a scene holds beyond its targets, clutter shapes and a plain table.
/// The default adds nothing and draws nothing, so scenes stay what they
/// were for the same seed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SceneStyle {
    /// Patterned table top, clutter and backdrop (`primitives::Texture`).
    pub textured: bool,
    /// Up to this many meshes from [`ModelLibrary::distractors`] stand among
    /// the targets, unannotated, as other objects do in a real scene.
    pub distractors: u32,
    /// Targets stand with their canonical +y axis up (the category frame:
    /// mugs, bowls, bottles and cans stand on their base; the object's own
    /// +y without a category entry) at a uniform yaw, instead of on a
    /// random face of their box.
    pub upright: bool,
    /// Each scene holds this many of the library's objects, drawn anew per
    /// scene (0: every object): thousands of generated instances make
    /// scenes of a few each. Drawn first, so it changes where the others go.
    pub objects_per_scene: u32,
}

/// The rotation that stands an object with its +y axis along world +z,
/// turned `yaw` about that axis.
fn upright_rotation(yaw: f64) -> Rotation3<f64> {
    let stand = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2);
    Rotation3::from_axis_angle(&Vector3::z_axis(), yaw) * stand
}

/// The rotation that puts one of the six faces of the object's bounding
/// box down, chosen with probability proportional to the face's area (a
/// cheap stand-in for the stability of a resting pose), then a uniform yaw.
fn resting_rotation<R: Rng + ?Sized>(extents: &Vector3<f32>, rng: &mut R) -> Rotation3<f64> {
    let areas = [extents.y * extents.z, extents.x * extents.z, extents.x * extents.y];
    let total: f32 = areas.iter().sum::<f32>().max(f32::MIN_POSITIVE);
    let mut pick = rng.random_range(0.0..total);
    let mut axis = 2;
    for (i, area) in areas.iter().enumerate() {
        if pick < *area {
            axis = i;
            break;
        }
        pick -= area;
    }
    let mut down = Vector3::zeros();
    down[axis] = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    // Rotates the chosen object axis onto world −z (a half turn when it is
    // already +z, where `rotation_between` has no unique answer).
    let tilt = Rotation3::rotation_between(&down, &-Vector3::z())
        .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), rng.random_range(0.0..std::f64::consts::TAU));
    yaw * tilt
}

/// Non-overlapping discs in a disk that grows when it gets too full.
struct Placer {
    radius: f64,
    placed: Vec<(Vector3<f64>, f64)>,
    gap: f64,
}

impl Placer {
    fn place<R: Rng + ?Sized>(&mut self, footprint: f64, rng: &mut R) -> Vector3<f64> {
        loop {
            for _ in 0..100 {
                let r = self.radius * rng.random::<f64>().sqrt();
                let angle = rng.random_range(0.0..std::f64::consts::TAU);
                let candidate = Vector3::new(r * angle.cos(), r * angle.sin(), 0.0);
                if self.placed.iter().all(|(c, f)| (c - candidate).norm() >= f + footprint + self.gap) {
                    self.placed.push((candidate, footprint));
                    return candidate;
                }
            }
            self.radius *= 1.2;
        }
    }
}

/// Draws a scene with one instance of every object in `library`.
pub fn compose_scene<R: Rng + ?Sized>(library: &ModelLibrary, occlusion: Occlusion, rng: &mut R) -> Scene {
    compose_styled_scene(library, occlusion, &SceneStyle::default(), rng)
}

/// [`compose_scene`] with `style`'s extras, drawn after everything else:
/// the same seed places targets and clutter where [`compose_scene`] does.
pub fn compose_styled_scene<R: Rng + ?Sized>(
    library: &ModelLibrary,
    occlusion: Occlusion,
    style: &SceneStyle,
    rng: &mut R,
) -> Scene {
    let crowding = occlusion.crowding();
    let every = library.objects.len();
    let chosen: Vec<usize> = match style.objects_per_scene as usize {
        k if k == 0 || k >= every => (0..every).collect(),
        k => {
            let mut drawn = rand::seq::index::sample(rng, every, k).into_vec();
            drawn.sort_unstable();
            drawn
        }
    };
    let mut rested = Vec::with_capacity(chosen.len());
    for &index in &chosen {
        let object = &library.objects[index];
        let (min, max) = object.model.mesh.bounds();
        let rotation = if style.upright {
            upright_rotation(rng.random_range(0.0..std::f64::consts::TAU)) * object.canonical_from_model.rotation
        } else {
            resting_rotation(&(max - min), rng)
        };
        let rotated: Vec<Vector3<f64>> =
            object.model.mesh.vertices.iter().map(|v| rotation * v.coords.cast::<f64>()).collect();
        let lowest = rotated.iter().map(|v| v.z).fold(f64::INFINITY, f64::min);
        let highest = rotated.iter().map(|v| v.z).fold(f64::NEG_INFINITY, f64::max);
        let footprint = rotated.iter().map(|v| v.xy().norm()).fold(0.0, f64::max);
        rested.push((rotation, -lowest, highest - lowest, footprint));
    }
    let covered: f64 = rested.iter().map(|r| std::f64::consts::PI * r.3 * r.3).sum();
    let mut placer = Placer {
        radius: (covered / (std::f64::consts::PI * f64::from(crowding.packing))).sqrt(),
        placed: Vec::new(),
        gap: f64::from(crowding.gap),
    };
    let mut objects = Vec::with_capacity(rested.len());
    for (&library_index, (rotation, lift, _, footprint)) in chosen.iter().zip(&rested) {
        let at = placer.place(*footprint, rng);
        objects.push(SceneObject {
            obj_id: library.objects[library_index].obj_id,
            library_index,
            world_from_object: Pose::new(*rotation, at + Vector3::z() * *lift),
        });
    }
    let spread = placer.radius;
    let mut diameters: Vec<f64> = chosen.iter().map(|&i| library.objects[i].info.diameter).collect();
    diameters.sort_by(f64::total_cmp);
    let typical = diameters.get(diameters.len() / 2).copied().unwrap_or(0.1) as f32;
    let count = rng.random_range(crowding.clutter_count.0..=crowding.clutter_count.1);
    let clutter = (0..count)
        .map(|_| {
            let shape = ClutterShape::random(crowding.clutter_size * typical, rng);
            let color = random_color(rng);
            let at = placer.place(f64::from(shape.footprint_radius()), rng);
            let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), rng.random_range(0.0..std::f64::consts::TAU));
            let model = RenderModel::new(shape.mesh(color)).expect("procedural shapes are valid meshes");
            (model, Pose::new(yaw, at))
        })
        .collect();
    let table = random_color(rng);
    let plane = RenderModel::new(support_plane(1.5, 48, table, rng)).expect("the plane is a valid mesh");
    let mean_height = rested.iter().map(|r| r.2).sum::<f64>() / rested.len().max(1) as f64;
    let middle = objects.iter().map(|o| o.world_from_object.translation.xy()).sum::<nalgebra::Vector2<f64>>()
        / objects.len().max(1) as f64;
    let mut scene = Scene {
        objects,
        clutter,
        plane,
        centre: Point3::new(middle.x, middle.y, mean_height / 2.0),
        spread,
        background: random_color(rng),
        backdrop: None,
    };
    add_style(&mut scene, library, style, &mut placer, rng);
    scene
}

/// `style`'s extras: distractors placed around the targets (the placement
/// disk grows if they do not fit), then patterns on the table, the clutter
/// and the backdrop.
fn add_style<R: Rng + ?Sized>(
    scene: &mut Scene,
    library: &ModelLibrary,
    style: &SceneStyle,
    placer: &mut Placer,
    rng: &mut R,
) {
    if style.distractors > 0 && !library.distractors.is_empty() {
        let count = rng.random_range(0..=style.distractors);
        for _ in 0..count {
            let object = &library.distractors[rng.random_range(0..library.distractors.len())];
            let (min, max) = object.model.mesh.bounds();
            let rotation = resting_rotation(&(max - min), rng);
            let rotated: Vec<Vector3<f64>> =
                object.model.mesh.vertices.iter().map(|v| rotation * v.coords.cast::<f64>()).collect();
            let lowest = rotated.iter().map(|v| v.z).fold(f64::INFINITY, f64::min);
            let footprint = rotated.iter().map(|v| v.xy().norm()).fold(0.0, f64::max);
            let at = placer.place(footprint, rng);
            scene.clutter.push((object.model.clone(), Pose::new(rotation, at - Vector3::z() * lowest)));
        }
    }
    if style.textured {
        // Table tops and clutter in centimetre-to-decimetre patterns; the
        // backdrop in image pixels.
        scene.plane.texture = Some(Texture::random(random_color(rng), (0.02, 0.25), rng));
        for (model, _) in &mut scene.clutter {
            if rng.random_bool(0.5) && model.texture.is_none() {
                let base = model.mesh.colors.as_ref().and_then(|c| c.first().copied()).unwrap_or([128; 3]);
                model.texture = Some(Texture::random(base, (0.005, 0.05), rng));
            }
        }
        scene.backdrop = Some(Texture::random(scene.background, (8.0, 120.0), rng));
    }
}

fn random_color<R: Rng + ?Sized>(rng: &mut R) -> [u8; 3] {
    [rng.random_range(30..=230), rng.random_range(30..=230), rng.random_range(30..=230)]
}

/// Where cameras may stand: distance to the look-at point, elevation above
/// the table, and roll about the optical axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewRange {
    pub distance: (f64, f64),
    pub elevation_deg: (f64, f64),
    pub max_in_plane_deg: f64,
}

impl Default for ViewRange {
    /// Distances like LM-O's (0.35–1.5 m), from just above the table to
    /// almost straight down, hand-held roll up to ±45°.
    fn default() -> Self {
        Self { distance: (0.35, 1.5), elevation_deg: (10.0, 85.0), max_in_plane_deg: 45.0 }
    }
}

impl ViewRange {
    /// A `camera_from_world` pose on the hemisphere around `scene.centre`,
    /// uniform in area over the elevation band, looking at a point jittered
    /// within half the scene's spread so objects are not always centred.
    pub fn sample<R: Rng + ?Sized>(&self, scene: &Scene, rng: &mut R) -> Pose {
        let distance = rng.random_range(self.distance.0..=self.distance.1);
        let (lo, hi) = (self.elevation_deg.0.to_radians().sin(), self.elevation_deg.1.to_radians().sin());
        let elevation = rng.random_range(lo..=hi).asin();
        let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
        let jitter = scene.spread * 0.5 * rng.random::<f64>().sqrt();
        let jitter_angle = rng.random_range(0.0..std::f64::consts::TAU);
        let target = scene.centre + Vector3::new(jitter * jitter_angle.cos(), jitter * jitter_angle.sin(), 0.0);
        let eye = target
            + distance
                * Vector3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
        let roll = rng.random_range(-self.max_in_plane_deg..=self.max_in_plane_deg).to_radians();
        look_at(&eye, &target, roll)
    }
}

/// The `camera_from_world` pose of an OpenCV camera (x right, y down, z
/// forward) at `eye` looking at `target` with the world's z up, then rolled
/// by `roll` radians about its optical axis. `eye` must not be straight
/// above `target`.
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>, roll: f64) -> Pose {
    look_at_up(eye, target, &Vector3::z(), roll)
}

/// [`look_at`] with `up` (any length) as the direction that appears upwards
/// in the image; `eye`, `target` and `up` are in one frame, the result maps
/// it into the camera's. The line of sight must not be parallel to `up`.
pub fn look_at_up(eye: &Point3<f64>, target: &Point3<f64>, up: &Vector3<f64>, roll: f64) -> Pose {
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let down = forward.cross(&right);
    let frame_from_camera =
        Rotation3::from_basis_unchecked(&[right, down, forward]) * Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
    Pose::new(frame_from_camera, eye.coords).inverse()
}

/// A light from the camera's side of the scene: direction within 80° of
/// the optical axis (pointing back at the camera), ambient share 0.15–0.5.
pub fn random_light<R: Rng + ?Sized>(rng: &mut R) -> Light {
    let cos_limit = 10f64.to_radians().sin();
    let z = -rng.random_range(cos_limit..=1.0);
    let angle = rng.random_range(0.0..std::f64::consts::TAU);
    let r = (1.0 - z * z).sqrt();
    Light { direction: Vector3::new(r * angle.cos(), r * angle.sin(), z), ambient: rng.random_range(0.15..=0.5) }
}

/// One camera view of a scene.
#[derive(Debug, Clone)]
pub struct View {
    /// Labels `1..=n` are the scene's objects in order; larger labels are
    /// clutter and the table.
    pub frame: Frame,
    /// `camera_from_object` of each scene object.
    pub object_poses: Vec<Pose>,
    /// Each object's full silhouette (as if alone), row-major.
    pub silhouettes: Vec<Vec<bool>>,
    /// Each object's silhouette pixels beyond the image border
    /// ([`truncated_pixels`]): with the silhouette's, BOP's `px_count_all`.
    pub truncated: Vec<u64>,
}

/// Renders `scene` from `camera_from_world`, with the scene background
/// where nothing is hit.
pub fn render_view(
    library: &ModelLibrary,
    scene: &Scene,
    camera: &Camera,
    camera_from_world: &Pose,
    light: &Light,
) -> View {
    let object_poses: Vec<Pose> = scene.objects.iter().map(|o| *camera_from_world * o.world_from_object).collect();
    let clutter_poses: Vec<Pose> = scene.clutter.iter().map(|(_, pose)| *camera_from_world * *pose).collect();
    let targets: Vec<Placed<'_>> = scene
        .objects
        .iter()
        .zip(&object_poses)
        .map(|(o, pose)| Placed { model: &library.objects[o.library_index].model, pose })
        .collect();
    let mut everything = targets.clone();
    everything.extend(scene.clutter.iter().zip(&clutter_poses).map(|((model, _), pose)| Placed { model, pose }));
    everything.push(Placed { model: &scene.plane, pose: camera_from_world });
    let mut frame = render(camera, &everything, light);
    let width = camera.width as usize;
    for (i, (rgb, _)) in frame.rgb.iter_mut().zip(&frame.label).enumerate().filter(|(_, (_, label))| **label == 0) {
        *rgb = match &scene.backdrop {
            Some(texture) => {
                texture.colour_at((i % width) as f32, (i / width) as f32).map(|c| (c * 255.0).round() as u8)
            }
            None => scene.background,
        };
    }
    let truncated = targets.iter().map(|target| truncated_pixels(camera, target)).collect();
    View { frame, silhouettes: silhouettes(camera, &targets), truncated, object_poses }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_puts_the_target_on_the_optical_axis_and_up_upwards() {
        let eye = Point3::new(1.0, -0.5, 0.8);
        let target = Point3::new(0.1, 0.2, 0.05);
        let camera_from_world = look_at(&eye, &target, 0.0);
        let seen = camera_from_world.transform_point(&target);
        assert!(seen.x.abs() < 1e-12 && seen.y.abs() < 1e-12, "{seen}");
        assert!((seen.z - (target - eye).norm()).abs() < 1e-12);
        // A point above the target is higher in the image: smaller y.
        let above = camera_from_world.transform_point(&(target + Vector3::z() * 0.1));
        assert!(above.y < -0.01, "{above}");
        assert!((camera_from_world.rotation.matrix().determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn roll_turns_the_image_about_the_optical_axis() {
        let eye = Point3::new(0.0, -1.0, 1.0);
        let target = Point3::origin();
        let above = target + Vector3::z() * 0.1;
        let level = look_at(&eye, &target, 0.0).transform_point(&above);
        let rolled = look_at(&eye, &target, std::f64::consts::FRAC_PI_2).transform_point(&above);
        // A quarter roll of the camera swaps the image axes of the offset.
        assert!((rolled.x.abs() - level.y.abs()).abs() < 1e-12 && rolled.y.abs() < 1e-12, "{level} {rolled}");
    }

    #[test]
    fn upright_rotation_stands_plus_y_up_at_its_yaw() {
        for yaw in [0.0, 1.0, -2.5] {
            let r = upright_rotation(yaw);
            assert!((r * Vector3::y() - Vector3::z()).norm() < 1e-12, "+y up");
            // Object +x turns in the table plane by the yaw.
            let x = r * Vector3::x();
            assert!((x - Vector3::new(yaw.cos(), yaw.sin(), 0.0)).norm() < 1e-12, "{x:?}");
        }
    }

    #[test]
    fn resting_rotation_puts_a_box_face_down() {
        let mut rng = poseflow_geometry::sampling::seeded_rng(4);
        let extents = Vector3::new(0.1, 0.05, 0.02);
        for _ in 0..50 {
            let r = resting_rotation(&extents, &mut rng);
            // Some object axis maps onto world ±z exactly.
            let vertical = (0..3).filter(|&i| (r.matrix()[(2, i)].abs() - 1.0).abs() < 1e-9).count();
            assert_eq!(vertical, 1, "{r:?}");
        }
    }
}
