//! The `ros2-bridge` stage's output as a ROS 2 subscriber sees it, read
//! back by a plain Zenoh session on loopback: the rmw_zenoh key of each
//! topic, the attachment, the liveliness tokens `ros2 topic list` reads,
//! and the CDR messages decoding to the Estimate's pose and hypotheses.
//! (The e2e tests check the same against an independent ROS 2 client.)

use std::time::{Duration, Instant};

use poseflow_contracts::{EstimateHeader, SelectionMethod, StampSlot};
use poseflow_geometry::Pose;
use poseflow_geometry::nalgebra::{Rotation3, Vector3};
use poseflow_ros2::msgs::{PoseArray, PoseWithCovarianceStamped};
use poseflow_ros2::rmw::Attachment;
use poseflow_ros2::stage::PosePublisher;
use poseflow_runtime::{Input, Sink};
use zenoh::Wait;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

#[test]
fn estimates_reach_a_zenoh_subscriber_as_ros_messages() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let params = serde_json::json!({ "listen": [endpoint], "connect": [], "domain_id": 42, "frame_id": "cam_optical" });
    let mut publisher = PosePublisher::from_params(&params).expect("the stage opens");

    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]")).unwrap();
    config.insert_json5("scouting/multicast/enabled", "false").unwrap();
    let session = zenoh::open(config).wait().unwrap();
    let samples = session.declare_subscriber("42/poseflow/**").wait().unwrap();

    let best = Pose::new(Rotation3::from_euler_angles(0.2, -0.4, 1.1), Vector3::new(0.03, -0.05, 0.7));
    let near = Pose::new(Rotation3::from_euler_angles(0.25, -0.4, 1.1), Vector3::new(0.035, -0.05, 0.7));
    let mut header = EstimateHeader {
        best: best.to_f32_row_major(),
        selection: SelectionMethod::Sdf as u32,
        hypothesis_count: 2,
        kept_count: 2,
        ..Default::default()
    };
    header.header.object_id = 5;
    header.header.stamps.ns[StampSlot::Source as usize] = 1_765_000_000_250_000_000;
    let payload: Vec<f32> = [best, near].iter().flat_map(|p| p.to_f32_row_major().into_iter().chain([0.0])).collect();

    // Publish until the subscription is known to the stage's session.
    let deadline = Instant::now() + Duration::from_secs(20);
    let (mut pose, mut array) = (None, None);
    while (pose.is_none() || array.is_none()) && Instant::now() < deadline {
        publisher.consume(Input { header: &header, payload: &payload }).unwrap();
        while let Ok(Some(sample)) = samples.recv_timeout(Duration::from_millis(100)) {
            let key = sample.key_expr().as_str().to_string();
            let attachment = Attachment::decode(&sample.attachment().expect("rmw_zenoh attachment").to_bytes());
            assert!(attachment.is_some_and(|a| a.sequence >= 1), "{key}");
            let bytes = sample.payload().to_bytes();
            if key
                .starts_with("42/poseflow/obj_000005/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_")
            {
                pose = Some(PoseWithCovarianceStamped::decode(&bytes).unwrap());
            } else if key.starts_with("42/poseflow/obj_000005/hypotheses/geometry_msgs::msg::dds_::PoseArray_/RIHS01_")
            {
                array = Some(PoseArray::decode(&bytes).unwrap());
            } else {
                panic!("unexpected key {key}");
            }
        }
    }
    let (pose, array) = (pose.expect("a pose within 20 s"), array.expect("hypotheses within 20 s"));
    assert_eq!((pose.header.stamp.sec, pose.header.stamp.nanosec), (1_765_000_000, 250_000_000));
    assert_eq!(pose.header.frame_id, "cam_optical");
    assert!((pose.pose.position[2] - 0.7).abs() < 1e-6);
    assert!(pose.covariance[21] > 0.0, "spread about x: {:?}", pose.covariance);
    assert_eq!(array.poses.len(), 2);

    let tokens: Vec<String> = session
        .liveliness()
        .get("@ros2_lv/42/**")
        .wait()
        .unwrap()
        .iter()
        .filter_map(|reply| reply.result().ok().map(|s| s.key_expr().as_str().to_string()))
        .collect();
    assert!(tokens.iter().any(|t| t.contains("/NN/%/%/poseflow")), "{tokens:?}");
    assert!(tokens.iter().any(|t| t.contains("/MP/%/%/poseflow/%poseflow%obj_000005%pose/")), "{tokens:?}");
}
