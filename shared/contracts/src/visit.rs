//! Choosing a contract header type by its name at run time (graph files and
//! recordings name message types as strings).

use crate::{
    ConditionHandle, EstimateHeader, FrameHeader, GraspsHeader, HypothesesHeader, MessageHeader, NextViewHeader,
    ObservationHeader, TensorHeader,
};

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
