//! The sampler ⇄ inference loop over request-response: N poses out, N
//! velocities back, K times, woken by events on both sides.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use poseflow_contracts::{Header, POSE_LEN, VELOCITY_LEN, VelocityRequest, VelocityResponse, status};
use poseflow_transport::{Ipc, RequestClient, RequestServer, create_node, edge_service_name};

const SAMPLES: u32 = 50;

#[test]
fn euler_steps_get_one_velocity_per_pose() {
    let name = edge_service_name(&format!("test-velocity-{}", std::process::id()), "velocity").unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let server = std::thread::spawn({
        let (name, stop) = (name.clone(), stop.clone());
        move || {
            let node = create_node("inference").unwrap();
            let server = RequestServer::<VelocityRequest, VelocityResponse>::create(&node, &name, 4096).unwrap();
            let waitset = WaitSetBuilder::new().create::<Ipc>().unwrap();
            let requests = waitset.attach_notification(&server).unwrap();
            let tick = waitset.attach_interval(Duration::from_millis(20)).unwrap();
            ready_tx.send(()).unwrap();
            let mut served = 0;
            waitset
                .wait_and_process(|id| {
                    if id.has_event_from(&requests) {
                        served += server
                            .serve(|request, poses, responder| {
                                let n = request.sample_count;
                                let header = VelocityResponse {
                                    header: request.header,
                                    request_id: request.request_id,
                                    sample_count: n,
                                    status: status::OK,
                                };
                                // A stand-in network: v = −t, ω = step index.
                                responder.send(header, n as usize * VELOCITY_LEN, |out| {
                                    for (i, v) in out.chunks_exact_mut(VELOCITY_LEN).enumerate() {
                                        let t = &poses[i * POSE_LEN + 9..i * POSE_LEN + 12];
                                        v[..3].copy_from_slice(&[-t[0], -t[1], -t[2]]);
                                        v[3..].fill(request.step_index as f32);
                                    }
                                })
                            })
                            .unwrap();
                    }
                    if id.has_event_from(&tick) && stop.load(Ordering::Relaxed) {
                        return CallbackProgression::Stop;
                    }
                    CallbackProgression::Continue
                })
                .unwrap();
            served
        }
    });
    ready_rx.recv().unwrap();

    let node = create_node("sampler").unwrap();
    let client = RequestClient::<VelocityRequest, VelocityResponse>::create(&node, &name, 4096).unwrap();
    for step in 0..5u32 {
        let request = VelocityRequest {
            step_index: step,
            step_count: 5,
            ..VelocityRequest::single(Header::new(9, 1), 77, u64::from(step), SAMPLES, step as f32 / 5.0)
        };
        let reply = client
            .call(
                request,
                SAMPLES as usize * POSE_LEN,
                |poses| {
                    for (i, pose) in poses.chunks_exact_mut(POSE_LEN).enumerate() {
                        pose.fill(0.0);
                        pose[9..].copy_from_slice(&[i as f32, 1.0, -2.0]);
                    }
                },
                Duration::from_secs(10),
            )
            .unwrap();
        assert_eq!(reply.header().request_id, u64::from(step));
        assert_eq!(reply.header().status, status::OK);
        let velocities = reply.payload();
        assert_eq!(velocities.len(), SAMPLES as usize * VELOCITY_LEN);
        assert_eq!(&velocities[6 * 7..6 * 8], &[-7.0, -1.0, 2.0, step as f32, step as f32, step as f32]);
    }
    stop.store(true, Ordering::Relaxed);
    assert_eq!(server.join().unwrap(), 5);
}

#[test]
fn a_call_without_server_fails_at_once_with_a_named_error() {
    let name = edge_service_name(&format!("test-noserver-{}", std::process::id()), "velocity").unwrap();
    let node = create_node("lonely-sampler").unwrap();
    let client = RequestClient::<VelocityRequest, VelocityResponse>::create(&node, &name, 64).unwrap();
    let request = VelocityRequest::single(Header::default(), 0, 0, 1, 0.0);
    // A timeout no test run reaches: the call must not wait it out.
    let err = client.call(request, POSE_LEN, |p| p.fill(0.0), Duration::from_secs(600)).unwrap_err().to_string();
    assert!(err.contains("no server") && err.contains("velocity"), "{err}");
}

#[test]
fn a_server_that_stops_without_answering_ends_the_call_before_its_timeout() {
    let name = edge_service_name(&format!("test-goneserver-{}", std::process::id()), "velocity").unwrap();
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let server = std::thread::spawn({
        let name = name.clone();
        move || {
            let node = create_node("vanishing-inference").unwrap();
            let server = RequestServer::<VelocityRequest, VelocityResponse>::create(&node, &name, 4096).unwrap();
            ready_tx.send(()).unwrap();
            // Takes the request, answers nothing and goes away.
            let waitset = WaitSetBuilder::new().create::<Ipc>().unwrap();
            let requests = waitset.attach_notification(&server).unwrap();
            let mut taken = 0;
            waitset
                .wait_and_process(|id| {
                    if id.has_event_from(&requests) {
                        taken += server.serve(|_, _, _| Ok(())).unwrap();
                    }
                    if taken > 0 { CallbackProgression::Stop } else { CallbackProgression::Continue }
                })
                .unwrap();
            taken
        }
    });
    ready_rx.recv().unwrap();
    let node = create_node("waiting-sampler").unwrap();
    let client = RequestClient::<VelocityRequest, VelocityResponse>::create(&node, &name, 64).unwrap();
    let request = VelocityRequest::single(Header::default(), 0, 0, 1, 0.0);
    let err = client.call(request, POSE_LEN, |p| p.fill(0.0), Duration::from_secs(600)).unwrap_err().to_string();
    assert!(err.contains("no server") && err.contains("velocity"), "{err}");
    assert_eq!(server.join().unwrap(), 1);
}
