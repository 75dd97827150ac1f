//! The Python stage module's ctypes mirrors of the contracts
//! (`plugins/python/poseflow_stage.py`) against the Rust layouts: size,
//! alignment, every field's offset, and the iceoryx2 type name a service
//! is opened with. A mismatch would corrupt every message silently or keep
//! the Python side from opening the service.

use std::collections::BTreeMap;
use std::mem::{align_of, offset_of, size_of};
use std::process::Command;

use iceoryx2::prelude::ZeroCopySend;
use poseflow_contracts::{
    CameraIntrinsics, ConditionHandle, EstimateHeader, FrameHeader, GraspsHeader, Header, Heartbeat, HypothesesHeader,
    NextViewHeader, ObservationHeader, StageStamps, TensorHeader, VelocityRequest, VelocityResponse,
};
use poseflow_e2e::plugin_python;
use serde_json::{Value, json};

/// `{size, align, type_name, fields: {name: offset}}` of one Rust contract.
macro_rules! rust_layout {
    ($t:ty { $($field:ident),* $(,)? }) => {
        (
            stringify!($t),
            json!({
                "size": size_of::<$t>(),
                "align": align_of::<$t>(),
                // SAFETY: reading the name has no precondition; the trait is
                // unsafe for its implementors, who promise the layout.
                "type_name": unsafe { <$t as ZeroCopySend>::type_name() },
                "fields": { $(stringify!($field): offset_of!($t, $field)),* },
            }),
        )
    };
}

/// Contracts that only ever travel inside another header.
const NESTED: [&str; 3] = ["StageStamps", "Header", "CameraIntrinsics"];

const DUMP: &str = r#"
import ctypes, json, sys
sys.path.insert(0, sys.argv[1])
import poseflow_stage as p
print(json.dumps({c.__name__: {
    "size": ctypes.sizeof(c),
    "align": ctypes.alignment(c),
    "type_name": c.type_name() if hasattr(c, "type_name") else None,
    "fields": {name: getattr(c, name).offset for name, _ in c._fields_},
} for c in p.CONTRACTS}))
"#;

#[test]
fn every_python_contract_mirror_has_the_rust_layout_and_type_name() {
    let rust: BTreeMap<&str, Value> = [
        rust_layout!(StageStamps { ns }),
        rust_layout!(Header { frame_id, object_id, flags, stamps }),
        rust_layout!(CameraIntrinsics { fx, fy, cx, cy, width, height }),
        rust_layout!(FrameHeader { header, intrinsics, scene_id, image_id, detection_count, mask_len }),
        rust_layout!(ObservationHeader {
            header,
            intrinsics,
            centroid,
            point_scale,
            crop,
            image_size,
            patch_grid,
            point_count,
            valid_point_count
        }),
        rust_layout!(ConditionHandle {
            header,
            condition_id,
            image_tokens,
            point_tokens,
            active_image_tokens,
            model_width,
            centroid,
            point_scale
        }),
        rust_layout!(VelocityRequest { header, condition_id, request_id, sample_count, t, step_index, step_count }),
        rust_layout!(VelocityResponse { header, request_id, sample_count, status }),
        rust_layout!(HypothesesHeader { header, sample_count, step_count }),
        rust_layout!(EstimateHeader {
            header,
            best,
            mean,
            covariance,
            rotation_trace,
            selection,
            mode_count,
            hypothesis_count,
            kept_count,
            refined
        }),
        rust_layout!(GraspsHeader { header, grasp_count, hypothesis_count }),
        rust_layout!(Heartbeat {
            header,
            pid,
            state,
            frames_in,
            frames_out,
            dropped,
            errors,
            latency_p50_us,
            latency_p99_us,
            busy_us,
            blocked_us
        }),
        rust_layout!(TensorHeader { header, shape, rank, reserved }),
        rust_layout!(NextViewHeader {
            header,
            chosen,
            expected_rotation_trace,
            current_rotation_trace,
            candidate_count,
            reserved
        }),
    ]
    .into_iter()
    .collect();
    let plugins = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python");
    let output = Command::new(plugin_python()).args(["-c", DUMP, plugins]).output().unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let python: BTreeMap<String, Value> = serde_json::from_slice(&output.stdout).unwrap();
    let names = |m: Vec<&str>| m.join(", ");
    assert_eq!(
        names(python.keys().map(String::as_str).collect()),
        names(rust.keys().copied().collect()),
        "a contract without its Python mirror, or the other way round"
    );
    for (name, expected) in &rust {
        let mirror = &python[*name];
        for key in ["size", "align", "fields"] {
            assert_eq!(
                mirror[key], expected[key],
                "{name}.{key}: Python {} against Rust {}",
                mirror[key], expected[key]
            );
        }
        // Structs nested in a header need no type name of their own in
        // Python: iceoryx2 matches only the header a service carries.
        if !mirror["type_name"].is_null() || !NESTED.contains(name) {
            assert_eq!(mirror["type_name"], expected["type_name"], "{name}: iceoryx2 type name");
        }
    }
}
