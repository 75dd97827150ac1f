//! Message decoding as a stage does it: a contract header (any bit
//! pattern: headers are plain integers and floats) checked against its
//! payload, then the typed views. Input: one byte choosing the message
//! type, the header's bytes, the payload as little-endian f32.
#![no_main]

use std::any::Any;

use libfuzzer_sys::fuzz_target;
use poseflow_contracts::{
    EstimateHeader, FrameHeader, MessageHeader, MessageVisitor, ObservationHeader, VelocityRequest, VelocityResponse,
    header_from_bytes, visit_message,
};

struct Decode<'a>(&'a [u8]);

impl Decode<'_> {
    fn check<H: MessageHeader + 'static>(self) {
        let size = std::mem::size_of::<H>();
        let Some(header) = self.0.get(..size).and_then(header_from_bytes::<H>) else { return };
        let payload: Vec<f32> =
            self.0[size..].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if header.check_payload(&payload).is_err() {
            return;
        }
        let header: &dyn Any = &header;
        if let Some(estimate) = header.downcast_ref::<EstimateHeader>() {
            let _ = estimate.view(&payload).map(|_| ());
            let _ = estimate.kept_poses(&payload).map(|poses| poses.count());
        } else if let Some(frame) = header.downcast_ref::<FrameHeader>() {
            let _ = frame.view(&payload).map(|_| ());
        } else if let Some(observation) = header.downcast_ref::<ObservationHeader>() {
            let _ = observation.view(&payload).map(|_| ());
        }
    }
}

impl MessageVisitor for Decode<'_> {
    type Output = ();
    fn visit<H: MessageHeader + Send + 'static>(self) {
        self.check::<H>()
    }
}

fuzz_target!(|bytes: &[u8]| {
    let Some((&kind, rest)) = bytes.split_first() else { return };
    let names = poseflow_graph::PUBLISH_SUBSCRIBE_MESSAGES;
    match usize::from(kind) % (names.len() + 2) {
        i if i < names.len() => {
            visit_message(names[i], Decode(rest));
        }
        i if i == names.len() => Decode(rest).check::<VelocityRequest>(),
        _ => Decode(rest).check::<VelocityResponse>(),
    }
});
