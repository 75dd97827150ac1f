//! One publisher, one subscriber, real iceoryx2 shared memory, woken by a
//! WaitSet: payloads arrive intact and end-of-stream is seen.

use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use poseflow_contracts::{Header, HypothesesHeader, MessageHeader, POSE_LEN};
use poseflow_transport::{EdgeOptions, EdgeSubscriber, Ipc, Publisher, create_node, edge_service_name};

#[test]
fn samples_and_end_of_stream_cross_shared_memory() {
    let instance = format!("test-roundtrip-{}", std::process::id());
    let name = edge_service_name(&instance, "poses").unwrap();
    let options = EdgeOptions { queue: 16, ..EdgeOptions::default() };
    let node = create_node("roundtrip").unwrap();
    let subscriber = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();

    let sender = std::thread::spawn({
        let name = name.clone();
        move || {
            let node = create_node("roundtrip-sender").unwrap();
            let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
            publisher.wait_for_receivers(1, std::time::Duration::from_secs(10)).unwrap();
            for frame in 0..10u64 {
                let header = HypothesesHeader {
                    header: Header::new(frame, 3),
                    sample_count: 2,
                    step_count: 5,
                    ..Default::default()
                };
                publisher
                    .publish(header, 2 * POSE_LEN, |p| {
                        p.iter_mut().enumerate().for_each(|(i, v)| *v = (frame * 100 + i as u64) as f32)
                    })
                    .unwrap();
            }
            // Returns once the subscriber has drained and acknowledged, so
            // dropping the publisher afterwards loses nothing.
            publisher.end_of_stream(std::time::Duration::from_secs(10)).unwrap()
        }
    });
    drop(publisher);

    let waitset = WaitSetBuilder::new().create::<Ipc>().unwrap();
    let guard = waitset.attach_notification(&subscriber).unwrap();
    let mut frames = Vec::new();
    let mut ended = false;
    while !ended {
        waitset
            .wait_and_process_once(|id| {
                if id.has_event_from(&guard) {
                    ended = subscriber.take_events().unwrap();
                    while let Some(msg) = subscriber.receive().unwrap() {
                        msg.header().check_payload(msg.payload()).unwrap();
                        let frame = msg.header().header.frame_id;
                        assert_eq!(msg.payload()[5], (frame * 100 + 5) as f32);
                        frames.push(frame);
                    }
                }
                CallbackProgression::Continue
            })
            .unwrap();
    }
    subscriber.acknowledge_end().unwrap();
    let end = sender.join().unwrap();
    assert_eq!(end.receivers, 1);
    assert_eq!(end.acknowledged, 1);
    assert_eq!(frames, (0..10).collect::<Vec<_>>());
}

#[test]
fn publish_rejects_a_payload_that_disagrees_with_its_header() {
    let name = edge_service_name(&format!("test-reject-{}", std::process::id()), "poses").unwrap();
    let node = create_node("reject").unwrap();
    let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &EdgeOptions::default()).unwrap();
    let header = HypothesesHeader { header: Header::new(0, 1), sample_count: 2, step_count: 1, ..Default::default() };
    let err = publisher.publish(header, 23, |_| {}).unwrap_err().to_string();
    assert!(err.contains("Hypotheses") && err.contains("24"), "{err}");
}
