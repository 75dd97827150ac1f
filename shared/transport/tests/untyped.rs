//! Ports opened by message name carry any contract message as its header's
//! bytes and its payload, unchanged, and refuse what does not fit.

use std::time::Duration;

use poseflow_contracts::{Header, HypothesesHeader, MessageHeader, POSE_LEN, header_bytes};
use poseflow_transport::{
    EdgeOptions, EdgeSubscriber, Overflow, Publisher, TransportError, create_node, edge_service_name,
    untyped_publisher, untyped_subscriber,
};

fn options() -> EdgeOptions {
    EdgeOptions { queue: 8, overflow: Overflow::Block, max_payload_len: 4096 }
}

#[test]
fn an_untyped_publisher_and_subscriber_carry_messages_byte_for_byte() {
    let name = edge_service_name(&format!("test-untyped-{}", std::process::id()), "poses").unwrap();
    let node = create_node("untyped-test").unwrap();
    // Typed writer → untyped reader → untyped writer → typed reader: what a
    // bridge does, on one machine.
    let typed_out = Publisher::<HypothesesHeader>::create(&node, &name, &options()).unwrap();
    let untyped_in = untyped_subscriber(&node, HypothesesHeader::NAME, &name, &options()).unwrap();
    let relayed = format!("{name}-relayed");
    let untyped_out = untyped_publisher(&node, HypothesesHeader::NAME, &relayed, &options()).unwrap();
    let typed_in = EdgeSubscriber::<HypothesesHeader>::create(&node, &relayed, &options()).unwrap();
    assert_eq!(typed_out.wait_for_receivers(1, Duration::from_secs(5)).unwrap(), 1);
    assert_eq!(untyped_out.wait_for_all_receivers(1, Duration::from_secs(5)).unwrap(), 1);

    let mut header =
        HypothesesHeader { header: Header::new(7, 3), sample_count: 2, step_count: 5, ..Default::default() };
    header.header.flags = 0b10;
    let payload: Vec<f32> = (0..2 * POSE_LEN).map(|i| f32::from_bits(0x3f80_0000 + i as u32)).collect();
    typed_out.publish(header, payload.len(), |out| out.copy_from_slice(&payload)).unwrap();

    let mut seen = None;
    assert!(untyped_in.take_events().is_ok());
    let received =
        untyped_in.receive_with(&mut |bytes, values| seen = Some((bytes.to_vec(), values.to_vec()))).unwrap();
    assert!(received);
    let (bytes, values) = seen.unwrap();
    assert_eq!(bytes, header_bytes(&header));
    let common = untyped_out.publish_bytes(&bytes, &values).unwrap();
    assert_eq!((common.frame_id, common.object_id, common.flags), (7, 3, 0b10));

    let message = typed_in.receive().unwrap().expect("the relayed message");
    assert_eq!(header_bytes(message.header()), header_bytes(&header));
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(message.payload()), bits(&payload));

    // A header of the wrong size, a payload its header does not announce,
    // and a message name no contract has are refused with what was expected.
    let err = untyped_out.publish_bytes(&bytes[1..], &values).unwrap_err();
    assert!(matches!(err, TransportError::HeaderSize { message: "Hypotheses", .. }), "{err}");
    let err = untyped_out.publish_bytes(&bytes, &values[1..]).unwrap_err();
    assert!(matches!(err, TransportError::Contract(_)), "{err}");
    let err = untyped_subscriber(&node, "Pose", &name, &options()).unwrap_err();
    assert!(err.to_string().contains("\"Pose\" is not a contract message"), "{err}");
    assert!(!untyped_in.receive_with(&mut |_, _| {}).unwrap(), "nothing more queued");
}
