//! Recordings compared message by message, bit for bit.

use std::path::Path;

/// A recorded message's header without what differs between any two runs:
/// the timestamps, and the inference stage's per-run condition ids.
pub fn without_stamps(message: &str, header: &[u8]) -> Vec<u8> {
    use poseflow_contracts::{
        ConditionHandle, MessageHeader, MessageVisitor, StageStamps, header_bytes, header_from_bytes,
    };

    if message == ConditionHandle::NAME {
        let mut handle: ConditionHandle = header_from_bytes(header).expect("a Condition header");
        handle.header.stamps = StageStamps::default();
        handle.condition_id = 0;
        return header_bytes(&handle);
    }
    struct Zeroed<'a>(&'a [u8]);
    impl MessageVisitor for Zeroed<'_> {
        type Output = Vec<u8>;
        fn visit<H: MessageHeader + Send + 'static>(self) -> Vec<u8> {
            let mut header: H = header_from_bytes(self.0).expect("a header of the edge's type");
            header.header_mut().stamps = StageStamps::default();
            header_bytes(&header)
        }
    }
    poseflow_contracts::visit_message(message, Zeroed(header)).expect("a contract message")
}

/// Per edge: the messages in order, as (header without stamps, payload bits).
pub type EdgeMessages = std::collections::BTreeMap<String, Vec<(Vec<u8>, Vec<u32>)>>;

pub fn recorded_messages(recording: &Path) -> EdgeMessages {
    use poseflow_runtime::recording::RecordingReader;

    let mut reader = RecordingReader::open(recording).unwrap();
    let types: std::collections::BTreeMap<String, String> =
        reader.info.edges.iter().map(|e| (e.edge.clone(), e.message.clone())).collect();
    let mut edges = EdgeMessages::new();
    while let Some(message) = reader.next_message().unwrap() {
        let header = without_stamps(&types[&message.edge], &message.header);
        let bits = message.payload.iter().map(|v| v.to_bits()).collect();
        edges.entry(message.edge).or_default().push((header, bits));
    }
    edges
}
