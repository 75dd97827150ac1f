//! The stored test vectors (shared with the Python training code) must be
//! what this crate computes: a change to the geometry that moves any number
//! fails here, and the vectors are regenerated deliberately or not at all.

use nalgebra::{Matrix3, Rotation3, Vector3};
use poseflow_geometry::pose::Twist;
use poseflow_geometry::vectors::{FORMAT, TestVectors, generate};
use poseflow_geometry::{Pose, flow, so3};

const PATH: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/vectors/se3_flow.json");

fn stored() -> TestVectors {
    let text = std::fs::read_to_string(PATH).expect("tests/vectors/se3_flow.json is in the repository");
    serde_json::from_str(&text).expect("vectors file parses")
}

fn rotation(values: &[f64; 9]) -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(values))
}

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

#[test]
fn stored_vectors_match_a_fresh_generation() {
    let stored = stored();
    assert_eq!(stored.format, FORMAT);
    let fresh = generate();
    assert_eq!(stored.so3_exp.len(), fresh.so3_exp.len());
    assert_eq!(stored.flow.len(), fresh.flow.len());
    // Bit-for-bit equality is not promised across CPUs (libm may round the
    // last ulp differently), 1e-12 is.
    let stored_json = serde_json::to_value(&stored).unwrap();
    let fresh_json = serde_json::to_value(&fresh).unwrap();
    assert_numbers_close(&stored_json, &fresh_json, 1e-12, "$");
}

fn assert_numbers_close(a: &serde_json::Value, b: &serde_json::Value, tol: f64, at: &str) {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= tol, "{at}: stored {x} vs computed {y}");
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (i, (x, y)) in x.iter().zip(y).enumerate() {
                assert_numbers_close(x, y, tol, &format!("{at}[{i}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (k, x) in x {
                assert_numbers_close(x, &y[k], tol, &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[test]
fn stored_vectors_are_self_consistent() {
    // Checks the relations the Python side will check, from the stored
    // numbers alone: exp/log invert each other, the path and the Euler step
    // follow their formulas.
    let v = stored();
    for case in &v.so3_exp {
        let omega = Vector3::from(case.omega);
        assert!(close(so3::exp(&omega).matrix().transpose().as_slice(), &case.rotation, 1e-12));
        if omega.norm() < std::f64::consts::PI - 1e-9 {
            assert!(close(so3::log(&rotation(&case.rotation)).as_slice(), &case.omega, 1e-9));
        }
    }
    for case in &v.se3_exp {
        let pose = Pose::exp(&Twist::from(case.twist));
        assert!(close(pose.translation.as_slice(), &case.translation, 1e-12));
        let back = Pose::new(rotation(&case.rotation), Vector3::from(case.translation)).log();
        assert!(close(back.as_slice(), &case.twist, 1e-9));
    }
    for case in &v.flow {
        let start = Pose::new(rotation(&case.r0), Vector3::from(case.p0));
        let target = Pose::new(rotation(&case.r1), Vector3::from(case.p1));
        let here = flow::interpolate(&start, &target, case.t);
        assert!(close(here.translation.as_slice(), &case.p_t, 1e-12));
        assert!(close(here.rotation.matrix().transpose().as_slice(), &case.r_t, 1e-9));
        let vel = flow::target_velocity(&here, &target, case.t).unwrap();
        assert!(close(vel.linear.as_slice(), &case.v_pos, 1e-9));
        assert!(close(vel.angular.as_slice(), &case.v_rot, 1e-6));
        let next_p = Vector3::from(case.p_t) + Vector3::from(case.v_pos) * case.dt;
        assert!(close(next_p.as_slice(), &case.p_next, 1e-12));
        let next_r = rotation(&case.r_t) * so3::exp(&(Vector3::from(case.v_rot) * case.dt));
        assert!(close(next_r.matrix().transpose().as_slice(), &case.r_next, 1e-9));
    }
}
