//! Procedural meshes for scenes: the support plane and clutter shapes.
//!
//! All in metres with the shape's base on `z = 0` (resting on the plane of
//! a z-up world frame) and its vertical axis through the origin.

use nalgebra::{Point3, Vector3};
use parry3d::shape::{Ball, Cuboid, Cylinder};
use rand::Rng;

use crate::ObjectMesh;

/// A square `2·half_extent` wide at `z = 0`, split into `cells × cells`
/// quads whose corner colours vary around `base`: a table top with a
/// low-frequency texture, so the background is not a flat colour the
/// network could learn to ignore trivially.
pub fn support_plane<R: Rng + ?Sized>(half_extent: f32, cells: u32, base: [u8; 3], rng: &mut R) -> ObjectMesh {
    let n = cells + 1;
    let step = 2.0 * half_extent / cells as f32;
    let mut vertices = Vec::with_capacity((n * n) as usize);
    let mut colors = Vec::with_capacity((n * n) as usize);
    for j in 0..n {
        for i in 0..n {
            vertices.push(Point3::new(-half_extent + i as f32 * step, -half_extent + j as f32 * step, 0.0));
            let shade: f32 = rng.random_range(0.8..1.2);
            colors.push(base.map(|c| (f32::from(c) * shade).round().clamp(0.0, 255.0) as u8));
        }
    }
    let mut triangles = Vec::with_capacity((2 * cells * cells) as usize);
    for j in 0..cells {
        for i in 0..cells {
            let a = j * n + i;
            triangles.push([a, a + 1, a + n + 1]);
            triangles.push([a, a + n + 1, a + n]);
        }
    }
    ObjectMesh { vertices, triangles, normals: Some(vec![Vector3::z(); (n * n) as usize]), colors: Some(colors) }
}

/// A procedural surface pattern in two colours, evaluated at a point of the
/// surface (metres, object frame; or pixels for an image backdrop): what
/// table tops, cloths and walls look like, so that a network cannot learn
/// that everything which is not a target is one flat colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Texture {
    pub kind: TextureKind,
    pub colours: [[u8; 3]; 2],
    /// Size of one period (checker square, stripe pair, noise cell).
    pub scale: f32,
    /// Direction of stripes and grain in the xy plane, radians.
    pub angle: f32,
    /// Seeds the noise lattice.
    pub seed: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextureKind {
    /// A chessboard (tiles, a tablecloth).
    Checker,
    /// Parallel bands with soft edges (planks, a striped cloth).
    Stripes,
    /// Smooth value noise (stone, a stained surface).
    Blotches,
    /// Stripes bent by noise (wood).
    Grain,
}

impl Texture {
    /// A random pattern whose first colour is `base`, the second a darker
    /// or lighter, possibly different hue; `scale` drawn from `scale_range`.
    pub fn random<R: Rng + ?Sized>(base: [u8; 3], scale_range: (f32, f32), rng: &mut R) -> Self {
        let kind = match rng.random_range(0..4) {
            0 => TextureKind::Checker,
            1 => TextureKind::Stripes,
            2 => TextureKind::Blotches,
            _ => TextureKind::Grain,
        };
        let other = if rng.random_bool(0.5) {
            let shade: f32 = rng.random_range(0.4..0.8);
            base.map(|c| (f32::from(c) * shade).round() as u8)
        } else {
            [rng.random_range(20..=235), rng.random_range(20..=235), rng.random_range(20..=235)]
        };
        Self {
            kind,
            colours: [base, other],
            scale: rng.random_range(scale_range.0..=scale_range.1),
            angle: rng.random_range(0.0..std::f32::consts::PI),
            seed: rng.random(),
        }
    }

    /// The colour (0–1 per channel) at `(x, y)`.
    pub fn colour_at(&self, x: f32, y: f32) -> [f32; 3] {
        let (s, c) = self.angle.sin_cos();
        let (along, across) = ((c * x + s * y) / self.scale, (-s * x + c * y) / self.scale);
        let mix = match self.kind {
            TextureKind::Checker => ((along.floor() + across.floor()).rem_euclid(2.0) == 0.0) as u8 as f32,
            TextureKind::Stripes => 0.5 + 0.5 * (std::f32::consts::TAU * across).sin().clamp(-0.6, 0.6) / 0.6,
            TextureKind::Blotches => value_noise(along, across, self.seed),
            TextureKind::Grain => {
                let bend = 2.0 * value_noise(along * 0.5, across * 0.5, self.seed);
                0.5 + 0.5 * (std::f32::consts::TAU * (across * 3.0 + bend)).sin()
            }
        };
        let [a, b] = self.colours.map(|c| c.map(|v| f32::from(v) / 255.0));
        [0, 1, 2].map(|k| a[k] + mix * (b[k] - a[k]))
    }
}

/// Smooth noise in [0, 1]: random values on the integer lattice, blended
/// with a smoothstep.
fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let lattice = |i: i32, j: i32| {
        let mut h = (i as u32).wrapping_mul(0x8DA6_B343) ^ (j as u32).wrapping_mul(0xD816_3841) ^ seed;
        h = (h ^ (h >> 13)).wrapping_mul(0x5BD1_E995);
        (h ^ (h >> 15)) as f32 / u32::MAX as f32
    };
    let (i, j) = (x.floor() as i32, y.floor() as i32);
    let (fx, fy) = (x - x.floor(), y - y.floor());
    let smooth = |t: f32| t * t * (3.0 - 2.0 * t);
    let (sx, sy) = (smooth(fx), smooth(fy));
    let top = lattice(i, j) + sx * (lattice(i + 1, j) - lattice(i, j));
    let bottom = lattice(i, j + 1) + sx * (lattice(i + 1, j + 1) - lattice(i, j + 1));
    top + sy * (bottom - top)
}

/// A distractor shape standing on the plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClutterShape {
    Box { half_extents: Vector3<f32> },
    Cylinder { radius: f32, height: f32 },
    Sphere { radius: f32 },
}

impl ClutterShape {
    /// A random shape whose largest dimension is at most `max_size`.
    pub fn random<R: Rng + ?Sized>(max_size: f32, rng: &mut R) -> Self {
        let kind = rng.random_range(0..3);
        let mut size = || rng.random_range(0.3 * max_size..=max_size);
        match kind {
            0 => Self::Box { half_extents: Vector3::new(size() / 2.0, size() / 2.0, size() / 2.0) },
            1 => Self::Cylinder { radius: size() / 2.0, height: size() },
            _ => Self::Sphere { radius: size() / 2.0 },
        }
    }

    /// The radius of the shape's footprint around its vertical axis.
    pub fn footprint_radius(&self) -> f32 {
        match *self {
            Self::Box { half_extents } => half_extents.xy().norm(),
            Self::Cylinder { radius, .. } | Self::Sphere { radius } => radius,
        }
    }

    /// The mesh in one flat colour, base on `z = 0`.
    pub fn mesh(&self, color: [u8; 3]) -> ObjectMesh {
        let (vertices, triangles) = match *self {
            Self::Box { half_extents } => lifted(Cuboid::new(half_extents).to_trimesh(), half_extents.z),
            Self::Cylinder { radius, height } => {
                // parry's cylinder axis is y; a quarter turn about x stands it up along z.
                let (vertices, triangles) = Cylinder::new(height / 2.0, radius).to_trimesh(24);
                let upright = vertices.into_iter().map(|p| Point3::new(p.x, -p.z, p.y)).collect();
                lifted((upright, triangles), height / 2.0)
            }
            Self::Sphere { radius } => lifted(Ball::new(radius).to_trimesh(12, 24), radius),
        };
        let colors = vec![color; vertices.len()];
        ObjectMesh { vertices, triangles, normals: None, colors: Some(colors) }
    }
}

fn lifted((vertices, triangles): (Vec<Point3<f32>>, Vec<[u32; 3]>), by: f32) -> (Vec<Point3<f32>>, Vec<[u32; 3]>) {
    (vertices.into_iter().map(|p| p + Vector3::z() * by).collect(), triangles)
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    #[test]
    fn clutter_stands_on_the_plane_within_its_footprint() {
        let mut rng = seeded_rng(3);
        for _ in 0..30 {
            let shape = ClutterShape::random(0.1, &mut rng);
            let mesh = shape.mesh([10, 20, 30]);
            let (min, max) = mesh.bounds();
            assert!(min.z.abs() < 1e-6, "{shape:?} starts at z = {}", min.z);
            assert!(max.z <= 0.1 + 1e-6 && max.z > 0.0, "{shape:?} is {} tall", max.z);
            let widest = mesh.vertices.iter().map(|p| p.coords.xy().norm()).fold(0.0, f32::max);
            assert!(widest <= shape.footprint_radius() + 1e-5, "{shape:?}: {widest}");
        }
    }

    #[test]
    fn textures_stay_between_their_two_colours_and_vary() {
        let mut rng = seeded_rng(8);
        for _ in 0..20 {
            let texture = Texture::random([200, 100, 50], (0.02, 0.2), &mut rng);
            let [a, b] = texture.colours.map(|c| c.map(|v| f32::from(v) / 255.0));
            let samples: Vec<[f32; 3]> =
                (0..400).map(|i| texture.colour_at((i % 20) as f32 * 0.013, (i / 20) as f32 * 0.017)).collect();
            for colour in &samples {
                for k in 0..3 {
                    let (low, high) = (a[k].min(b[k]), a[k].max(b[k]));
                    assert!(colour[k] >= low - 1e-5 && colour[k] <= high + 1e-5, "{texture:?}: {colour:?}");
                }
            }
            let distinct = samples.iter().filter(|c| (c[0] - samples[0][0]).abs() > 0.01).count();
            assert!(a == b || distinct > 20, "{texture:?} is almost flat: {distinct}");
        }
    }

    #[test]
    fn plane_is_flat_and_covers_the_square() {
        let plane = support_plane(0.5, 4, [100, 100, 100], &mut seeded_rng(1));
        assert_eq!((plane.vertices.len(), plane.triangles.len()), (25, 32));
        let (min, max) = plane.bounds();
        assert_eq!((min, max), (Point3::new(-0.5, -0.5, 0.0), Point3::new(0.5, 0.5, 0.0)));
    }
}
