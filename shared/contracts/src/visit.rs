//! Choosing a contract header type by its name at run time (graph files and
//! recordings name message types as strings).

use crate::{
    ConditionHandle, EstimateHeader, FrameHeader, GraspsHeader, HypothesesHeader, MessageHeader, NextViewHeader,
    ObservationHeader, TensorHeader,
};

/// Message types a publish-subscribe edge may carry, as graph files and
/// recordings name them: the `NAME` of each contract header
/// [`visit_message`] knows.
pub const PUBLISH_SUBSCRIBE_MESSAGES: [&str; 8] = [
    FrameHeader::NAME,
    ObservationHeader::NAME,
    ConditionHandle::NAME,
    HypothesesHeader::NAME,
    EstimateHeader::NAME,
    GraspsHeader::NAME,
    NextViewHeader::NAME,
    TensorHeader::NAME,
];

/// Message types a request-response edge may carry: "Velocity" is the
/// [`crate::VelocityRequest`] / [`crate::VelocityResponse`] pair.
pub const REQUEST_RESPONSE_MESSAGES: [&str; 1] = ["Velocity"];

/// Code that works for any publish-subscribe contract header.
pub trait MessageVisitor {
    type Output;
    fn visit<H: MessageHeader + Send + 'static>(self) -> Self::Output;
}

/// Calls `visitor` with the header type whose `NAME` is `message`; `None`
/// for an unknown name.
pub fn visit_message<V: MessageVisitor>(message: &str, visitor: V) -> Option<V::Output> {
    Some(match message {
        FrameHeader::NAME => visitor.visit::<FrameHeader>(),
        ObservationHeader::NAME => visitor.visit::<ObservationHeader>(),
        ConditionHandle::NAME => visitor.visit::<ConditionHandle>(),
        HypothesesHeader::NAME => visitor.visit::<HypothesesHeader>(),
        EstimateHeader::NAME => visitor.visit::<EstimateHeader>(),
        GraspsHeader::NAME => visitor.visit::<GraspsHeader>(),
        NextViewHeader::NAME => visitor.visit::<NextViewHeader>(),
        TensorHeader::NAME => visitor.visit::<TensorHeader>(),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Name;

    impl MessageVisitor for Name {
        type Output = &'static str;
        fn visit<H: MessageHeader + Send + 'static>(self) -> &'static str {
            H::NAME
        }
    }

    #[test]
    fn every_listed_message_is_visited_as_its_own_header_and_nothing_else_is() {
        for name in PUBLISH_SUBSCRIBE_MESSAGES {
            assert_eq!(visit_message(name, Name), Some(name));
        }
        for unknown in ["Velocity", "frame", "", "Heartbeat"] {
            assert_eq!(visit_message(unknown, Name), None, "{unknown}");
        }
    }
}
