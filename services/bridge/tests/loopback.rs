//! Two `zenoh-bridge` processes on this machine's loopback, wired as two
//! hosts' bridges for one edge: what a writer publishes on one side
//! arrives on the other byte for byte, in order, followed by the end of
//! the stream, and both bridges then exit cleanly.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use poseflow_contracts::{Header, HypothesesHeader, MessageHeader, POSE_LEN, header_bytes};
use poseflow_graph::{EdgeWiring, OverflowPolicy, WIRING_ENV};
use poseflow_transport::{EdgeOptions, EdgeSubscriber, Publisher, create_node};

#[test]
fn two_bridges_carry_an_edge_intact_and_end_with_its_stream() {
    let id = std::process::id();
    let edge = EdgeWiring {
        edge: "poses".into(),
        service: String::new(),
        message: HypothesesHeader::NAME.into(),
        queue: 4,
        overflow: OverflowPolicy::Block,
        max_payload_len: 4 * POSE_LEN,
        readers: 0,
    };
    let endpoint = format!("tcp/127.0.0.1:{}", 20_000 + id % 20_000);
    let instances = (format!("loop-a-{id}"), format!("loop-b-{id}"));
    let (sending, receiving) = poseflow_bridge::one_edge_wirings(
        &edge,
        &endpoint,
        &format!("poseflow/loopback-{id}"),
        (&instances.0, &instances.1),
    )
    .unwrap();
    let options =
        EdgeOptions { queue: 4, overflow: poseflow_transport::Overflow::Block, max_payload_len: 4 * POSE_LEN };
    let node = create_node("loopback-test").unwrap();
    let reader = EdgeSubscriber::<HypothesesHeader>::create(&node, &receiving.outputs[0].service, &options).unwrap();
    let writer = Publisher::<HypothesesHeader>::create(&node, &sending.inputs[0].service, &options).unwrap();
    let bridges: Vec<_> = [&receiving, &sending]
        .iter()
        .map(|wiring| {
            Command::new(env!("CARGO_BIN_EXE_zenoh-bridge"))
                .env(WIRING_ENV, wiring.to_json())
                .stdin(Stdio::null())
                .spawn()
                .unwrap()
        })
        .collect();
    // The sending bridge subscribes only once the receiving one is ready,
    // which needs this reader to answer the receiving bridge's handshake.
    let deadline = Instant::now() + Duration::from_secs(60);
    while writer.wait_for_receivers(1, Duration::from_millis(50)).unwrap() < 1 {
        reader.take_events().unwrap();
        assert!(Instant::now() < deadline, "the bridges never connected");
    }

    let messages: Vec<(HypothesesHeader, Vec<f32>)> = (0..40u64)
        .map(|frame| {
            let samples = 1 + (frame % 4) as u32;
            let mut header = HypothesesHeader {
                header: Header::new(frame, 5),
                sample_count: samples,
                step_count: 3,
                ..Default::default()
            };
            header.header.flags = (frame % 2) as u32;
            let payload = (0..samples as usize * POSE_LEN).map(|i| (frame * 100 + i as u64) as f32 * 0.5).collect();
            (header, payload)
        })
        .collect();
    // One message at a time: ports stay on this thread, and each message is
    // taken before the next is sent.
    let mut received = Vec::new();
    let mut ended = false;
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut take = |received: &mut Vec<(Vec<u8>, Vec<f32>)>| {
        ended |= reader.take_events().unwrap();
        while let Some(message) = reader.receive().unwrap() {
            received.push((header_bytes(message.header()), message.payload().to_vec()));
        }
        assert!(Instant::now() < deadline, "stuck after {} messages", received.len());
        std::thread::sleep(Duration::from_millis(1));
        ended
    };
    for (i, (header, payload)) in messages.iter().enumerate() {
        writer.publish(*header, payload.len(), |out| out.copy_from_slice(payload)).unwrap();
        while received.len() <= i {
            take(&mut received);
        }
    }
    let end = writer.end_of_stream(Duration::from_secs(30)).unwrap();
    while !take(&mut received) {}
    reader.acknowledge_end().unwrap();
    assert_eq!(end.receivers, 1);
    assert_eq!(received.len(), messages.len());
    for ((header, payload), (got_header, got_payload)) in messages.iter().zip(&received) {
        assert_eq!(&header_bytes(header), got_header);
        assert_eq!(
            payload.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            got_payload.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
    }
    for mut bridge in bridges {
        let deadline = Instant::now() + Duration::from_secs(30);
        let status = loop {
            if let Some(status) = bridge.try_wait().unwrap() {
                break status;
            }
            if Instant::now() > deadline {
                let _ = bridge.kill();
                panic!("a bridge did not exit after the end of the stream");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        assert!(status.success(), "{status}");
    }
}
