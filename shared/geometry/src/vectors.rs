//! Reference input/output vectors of the flow geometry, shared with the
//! Python training code so both sides compute the same path and targets.
//!
//! The file is JSON (`tests/vectors/se3_flow.json` in the repository);
//! rotations are row-major 3×3 lists of 9 numbers, rotation vectors and
//! translations lists of 3, twists `[ρ; φ]` lists of 6.

use nalgebra::{Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::pose::Twist;
use crate::sampling::{TranslationNoise, initial_pose, seeded_rng, uniform_rotation};
use crate::{Pose, flow, so3};

pub const FORMAT: &str = "poseflow-se3-test-vectors/1";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TestVectors {
    pub format: String,
    pub conventions: String,
    pub so3_exp: Vec<So3Case>,
    pub se3_exp: Vec<Se3Case>,
    pub flow: Vec<FlowCase>,
}

/// `rotation = exp(omega)` and `omega = log(rotation)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct So3Case {
    pub omega: [f64; 3],
    pub rotation: [f64; 9],
}

/// `(rotation, translation) = exp(twist)` and `twist = log(...)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Se3Case {
    pub twist: [f64; 6],
    pub rotation: [f64; 9],
    pub translation: [f64; 3],
}

/// The path point at `t`, its target velocities, and one Euler step of
/// length `dt` with those velocities.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlowCase {
    pub r0: [f64; 9],
    pub p0: [f64; 3],
    pub r1: [f64; 9],
    pub p1: [f64; 3],
    pub t: f64,
    pub r_t: [f64; 9],
    pub p_t: [f64; 3],
    pub v_pos: [f64; 3],
    pub v_rot: [f64; 3],
    pub dt: f64,
    pub r_next: [f64; 9],
    pub p_next: [f64; 3],
}

pub fn rotation_row_major(r: &Rotation3<f64>) -> [f64; 9] {
    let m = r.matrix();
    std::array::from_fn(|i| m[(i / 3, i % 3)])
}

fn vec3(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn so3_case(omega: Vector3<f64>) -> So3Case {
    So3Case { omega: vec3(&omega), rotation: rotation_row_major(&so3::exp(&omega)) }
}

fn flow_case(start: Pose, target: Pose, t: f64, dt: f64) -> FlowCase {
    let here = flow::interpolate(&start, &target, t);
    let velocity = flow::target_velocity(&here, &target, t).expect("t < 1 by construction");
    let mut next = [here];
    flow::euler_step(&mut next, &[velocity], dt).expect("one velocity per pose");
    FlowCase {
        r0: rotation_row_major(&start.rotation),
        p0: vec3(&start.translation),
        r1: rotation_row_major(&target.rotation),
        p1: vec3(&target.translation),
        t,
        r_t: rotation_row_major(&here.rotation),
        p_t: vec3(&here.translation),
        v_pos: vec3(&velocity.linear),
        v_rot: vec3(&velocity.angular),
        dt,
        r_next: rotation_row_major(&next[0].rotation),
        p_next: vec3(&next[0].translation),
    }
}

/// The reference set: hand-picked edge cases (zero, tiny, near and at π)
/// followed by seeded random draws.
pub fn generate() -> TestVectors {
    use std::f64::consts::PI;
    let mut rng = seeded_rng(20_261_123);
    let axis = Vector3::new(2.0, -1.0, 0.5).normalize();

    let mut so3_exp: Vec<So3Case> =
        [0.0, 1e-9, 1e-6, 0.5, PI / 2.0, PI - 1e-6, PI].iter().map(|&angle| so3_case(axis * angle)).collect();
    so3_exp.extend((0..16).map(|_| so3_case(so3::log(&uniform_rotation(&mut rng)))));

    let noise = TranslationNoise::Gaussian { std_dev: 0.5 };
    let se3_exp = (0..16)
        .map(|i| {
            let pose = initial_pose(&mut rng, &noise);
            let twist: Twist = if i == 0 { Twist::zeros() } else { pose.log() };
            let pose = Pose::exp(&twist);
            Se3Case {
                twist: std::array::from_fn(|k| twist[k]),
                rotation: rotation_row_major(&pose.rotation),
                translation: vec3(&pose.translation),
            }
        })
        .collect();

    let mut flow_cases = Vec::new();
    // A start that is π − 1e-6 from the target about a fixed axis.
    let start = Pose::new(so3::exp(&(axis * 0.3)), Vector3::new(0.1, 0.2, 0.3));
    let far = Pose::new(start.rotation * so3::exp(&(axis * (PI - 1e-6))), Vector3::zeros());
    flow_cases.push(flow_case(start, far, 0.0, 0.2));
    flow_cases.push(flow_case(start, start, 0.5, 0.2));
    for k in 0..24 {
        let start = initial_pose(&mut rng, &noise);
        let target = initial_pose(&mut rng, &noise);
        let steps = [1, 5, 10][k % 3];
        let t = (k % steps) as f64 / steps as f64;
        flow_cases.push(flow_case(start, target, t, 1.0 / steps as f64));
    }

    TestVectors {
        format: FORMAT.to_string(),
        conventions: "Rotations row-major 3x3 (9 numbers). Poses are x_to = R x_from + t, \
            metres and radians. Rotation vectors are axis*angle with angle in [0, pi]; \
            angular velocities are body-frame: R(t+dt) = R(t) exp(dt v_rot). Twists are \
            [rho; phi] (translation part first), exp(twist) = (exp(phi), J_l(phi) rho). \
            Flow: p_t = (1-t) p0 + t p1, R_t = R0 exp(t log(R0^T R1)), v_pos = (p1 - p_t)/(1-t), \
            v_rot = log(R_t^T R1)/(1-t); Euler: R_next = R_t exp(dt v_rot), p_next = p_t + dt v_pos."
            .to_string(),
        so3_exp,
        se3_exp,
        flow: flow_cases,
    }
}
