//! Levenberg-Marquardt on SE(3) (beyond the paper): moves a pose so the
//! observed points lie on the object's surface, with residuals
//! `r_i = sdf(Rᵀ(x_i − t))` from the signed distance grid.
//!
//! Update (body frame): `R ← R exp(φ)`, `t ← t + R ρ`. To first order the
//! model-frame point moves by `δy = −ρ − φ × y`, so the Jacobian row of
//! `r_i` is `∇sdf(y_i)ᵀ [−I, [y_i]×]`. Residuals beyond `outlier_distance`
//! are ignored, the rest weighted by Huber at `noise_std`.

use nalgebra::{Matrix6, Point3, Vector3, Vector6};
use poseflow_geometry::{Pose, so3};

use crate::sdf::SignedDistanceGrid;

/// Likelihood settings, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Likelihood {
    pub noise_std: f64,
    pub outlier_distance: f64,
}

impl Likelihood {
    /// The log-likelihood of an outlier point: `−τ²/(2σ²)`.
    pub fn outlier_score(&self) -> f64 {
        -(self.outlier_distance * self.outlier_distance) / (2.0 * self.noise_std * self.noise_std)
    }
}

/// What a refinement did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refined {
    pub pose: Pose,
    /// Robust cost before and after (half the weighted sum of squares).
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
    /// Poses whose cost was evaluated (one pass over the points each).
    pub evaluations: usize,
}

/// A proposed step this small (metres, and radians about the body axes)
/// ends the refinement untaken: the pose is within about a micrometre of
/// where the steps lead, orders of magnitude below the depth noise, while
/// each further step costs a pass over the points, and at the optimum the
/// damping ladder's five tries cost five more.
pub const CONVERGED_STEP: f64 = 1e-6;

fn huber_weight(r: f64, delta: f64) -> f64 {
    if r.abs() <= delta { 1.0 } else { delta / r.abs() }
}

/// The normal equations `(JᵀWJ, JᵀWr)` of a pose, with its robust cost.
#[derive(Debug, Clone, Copy)]
struct System {
    cost: f64,
    jtj: Matrix6<f64>,
    jtr: Vector6<f64>,
}

/// The robust cost of `pose` and its normal equations. A refinement step
/// that is accepted goes on from the system evaluated to judge it, so each
/// iteration reads the grid once.
fn evaluate(grid: &SignedDistanceGrid, pose: &Pose, points: &[Point3<f64>], likelihood: &Likelihood) -> System {
    let inverse = pose.inverse();
    let mut system = System { cost: 0.0, jtj: Matrix6::zeros(), jtr: Vector6::zeros() };
    for x in points {
        let y = inverse.transform_point(x);
        let (r, gradient) = grid.value_and_gradient(&y);
        if r.abs() > likelihood.outlier_distance {
            continue;
        }
        let w = huber_weight(r, likelihood.noise_std);
        system.cost += 0.5 * w * r * r;
        // ∂r/∂ρ = −∇sdf, ∂r/∂φ = ∇sdfᵀ [y]× = (∇sdf × y)ᵀ.
        let rotational: Vector3<f64> = gradient.cross(&y.coords);
        let row = [-gradient.x, -gradient.y, -gradient.z, rotational.x, rotational.y, rotational.z];
        // The upper triangle only (JᵀWJ is symmetric); mirrored once below.
        for i in 0..6 {
            for j in i..6 {
                system.jtj[(i, j)] += row[i] * row[j] * w;
            }
            system.jtr[i] += row[i] * (w * r);
        }
    }
    system.jtj.fill_lower_triangle_with_upper_triangle();
    system
}

fn apply(pose: &Pose, step: &Vector6<f64>) -> Pose {
    let rho = Vector3::new(step[0], step[1], step[2]);
    let phi = Vector3::new(step[3], step[4], step[5]);
    Pose::new(pose.rotation * so3::exp(&phi), pose.translation + pose.rotation * rho)
}

/// Refines `pose` for `iterations` Levenberg-Marquardt steps at most.
pub fn refine(
    grid: &SignedDistanceGrid,
    pose: &Pose,
    points: &[Point3<f64>],
    likelihood: &Likelihood,
    iterations: usize,
) -> Refined {
    let mut current = *pose;
    let mut system = evaluate(grid, &current, points, likelihood);
    let mut evaluations = 1;
    let initial_cost = system.cost;
    let mut lambda = 1e-3;
    let mut done = 0;
    'iterations: while done < iterations {
        done += 1;
        // Raise the damping until a step lowers the cost (a few tries).
        for _ in 0..5 {
            let mut damped = system.jtj;
            for k in 0..6 {
                damped[(k, k)] += lambda * system.jtj[(k, k)].max(1e-9);
            }
            let Some(step) = damped.cholesky().map(|c| c.solve(&(-system.jtr))) else {
                lambda *= 10.0;
                continue;
            };
            if step.fixed_rows::<3>(0).norm() < CONVERGED_STEP && step.fixed_rows::<3>(3).norm() < CONVERGED_STEP {
                break 'iterations;
            }
            let candidate = apply(&current, &step);
            let judged = evaluate(grid, &candidate, points, likelihood);
            evaluations += 1;
            if judged.cost < system.cost {
                current = candidate;
                system = judged;
                lambda = (lambda / 3.0).max(1e-7);
                continue 'iterations;
            }
            lambda *= 5.0;
        }
        break;
    }
    let cost = system.cost;
    Refined { pose: current, initial_cost, final_cost: cost, iterations: done, evaluations }
}
