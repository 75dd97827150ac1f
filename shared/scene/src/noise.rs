//! A structured-light / time-of-flight depth sensor's errors, applied to a
//! clean rendered depth image, seeded and reproducible:
//!
//! - axial noise growing with distance, σ(z) = a + b (z − z₀)², after Nguyen
//!   et al. (2012) for the Kinect (a = 1.2 mm, b = 1.9 mm/m², z₀ = 0.4 m);
//! - dropout at depth edges (the sensor loses pixels next to a jump);
//! - random missing pixels.
//!
//! Missing depth is 0, as in BOP depth images.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// Parameters of [`DepthNoise::apply`]; lengths in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthNoise {
    pub sigma_base: f64,
    pub sigma_quadratic: f64,
    pub sigma_reference_depth: f64,
    /// A neighbour closer or farther by more than this marks a depth edge.
    pub edge_jump: f32,
    /// Probability that a pixel on a depth edge is lost.
    pub edge_dropout: f64,
    /// Probability that any other pixel is lost.
    pub missing: f64,
}

impl Default for DepthNoise {
    fn default() -> Self {
        Self {
            sigma_base: 0.0012,
            sigma_quadratic: 0.0019,
            sigma_reference_depth: 0.4,
            edge_jump: 0.02,
            edge_dropout: 0.5,
            missing: 0.002,
        }
    }
}

impl DepthNoise {
    /// Axial standard deviation at depth `z`.
    pub fn sigma(&self, z: f64) -> f64 {
        self.sigma_base + self.sigma_quadratic * (z - self.sigma_reference_depth).powi(2)
    }

    /// Returns a noisy copy of the row-major `depth` image (`width` wide).
    pub fn apply<R: Rng + ?Sized>(&self, depth: &[f32], width: usize, rng: &mut R) -> Vec<f32> {
        let height = depth.len() / width.max(1);
        let at = |u: usize, v: usize| depth[v * width + u];
        let mut out = depth.to_vec();
        for v in 0..height {
            for u in 0..width {
                let z = at(u, v);
                let i = v * width + u;
                if z <= 0.0 {
                    continue;
                }
                let neighbours = [(u.wrapping_sub(1), v), (u + 1, v), (u, v.wrapping_sub(1)), (u, v + 1)];
                let on_edge = neighbours.iter().any(|&(nu, nv)| {
                    nu < width && nv < height && {
                        let n = at(nu, nv);
                        n <= 0.0 || (n - z).abs() > self.edge_jump
                    }
                });
                let drop_probability = if on_edge { self.edge_dropout } else { self.missing };
                // Both draws happen for every valid pixel, so the random stream
                // does not depend on which branch is taken.
                let lost = rng.random::<f64>() < drop_probability;
                let gaussian: f64 = StandardNormal.sample(rng);
                out[i] = if lost { 0.0 } else { (f64::from(z) + gaussian * self.sigma(f64::from(z))).max(0.0) as f32 };
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    #[test]
    fn flat_wall_gets_the_modelled_spread_and_dropout() {
        let (w, h) = (200, 200);
        let depth = vec![1.5f32; w * h];
        let noise = DepthNoise::default();
        let noisy = noise.apply(&depth, w, &mut seeded_rng(5));
        let valid: Vec<f64> = noisy.iter().filter(|z| **z > 0.0).map(|z| f64::from(*z)).collect();
        let missing = (w * h - valid.len()) as f64 / (w * h) as f64;
        // Only random dropout inside; the image border has no edge.
        assert!((missing - noise.missing).abs() < 0.001, "{missing}");
        let mean = valid.iter().sum::<f64>() / valid.len() as f64;
        let std = (valid.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / valid.len() as f64).sqrt();
        let expected = noise.sigma(1.5); // 1.2 mm + 1.9 mm/m² · 1.1² m² ≈ 3.5 mm
        assert!((mean - 1.5).abs() < 1e-4, "{mean}");
        assert!((std - expected).abs() < 0.05 * expected, "{std} vs {expected}");
    }

    #[test]
    fn pixels_next_to_a_jump_drop_out_more_often() {
        let (w, h) = (100, 100);
        // Left half at 0.5 m, right half at 1.0 m: column 49/50 is an edge.
        let depth: Vec<f32> = (0..w * h).map(|i| if i % w < 50 { 0.5 } else { 1.0 }).collect();
        let noisy = DepthNoise::default().apply(&depth, w, &mut seeded_rng(9));
        let lost_on_edge = (0..h).filter(|v| noisy[v * w + 49] == 0.0).count();
        let lost_inside = (0..h).filter(|v| noisy[v * w + 20] == 0.0).count();
        assert!(lost_on_edge > 30 && lost_inside < 5, "{lost_on_edge} vs {lost_inside}");
        // Same seed, same image; another seed, another image.
        assert_eq!(noisy, DepthNoise::default().apply(&depth, w, &mut seeded_rng(9)));
        assert_ne!(noisy, DepthNoise::default().apply(&depth, w, &mut seeded_rng(10)));
    }
}
