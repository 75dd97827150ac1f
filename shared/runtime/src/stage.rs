//! What a stage author implements: plain functions from inputs to outputs,
//! with no transport in sight.

use std::time::Duration;

use poseflow_contracts::{Header, MessageHeader, StampSlot};

/// One received message, already checked against its contract.
#[derive(Debug, Clone, Copy)]
pub struct Input<'a, H> {
    pub header: &'a H,
    pub payload: &'a [f32],
}

impl<H: MessageHeader> Input<'_, H> {
    /// The common header to put on an output derived from this input: same
    /// frame, object, flags and the stamps collected so far.
    pub fn forward_header(&self) -> Header {
        *self.header.header()
    }
}

/// Where a stage sends its outputs. The runtime provides it: in a process it
/// writes straight into iceoryx2 shared memory, in-process into a channel.
pub trait Emitter<H: MessageHeader> {
    /// Publishes a message with a payload of `len` floats written by `fill`
    /// in place. `len` must equal `header.payload_len()`.
    fn emit(&mut self, header: H, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError>;
}

/// Why a message could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum EmitError {
    #[error("cannot send the message")]
    Transport(#[source] Box<poseflow_transport::TransportError>),
    #[error("{message}: the header's payload length")]
    Header {
        message: &'static str,
        #[source]
        source: poseflow_contracts::ContractError,
    },
    #[error("{message}: payload of {len} values, the header announces {expected}")]
    Length { message: &'static str, len: usize, expected: usize },
}

impl From<poseflow_transport::TransportError> for EmitError {
    fn from(err: poseflow_transport::TransportError) -> Self {
        // Boxed: every stage's error type carries an EmitError.
        Self::Transport(Box::new(err))
    }
}

/// Why [`Transform::flush`] is called.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flush {
    /// The input queue ran empty: more may come.
    Idle,
    /// The input ended, or the stage is stopping: nothing more will come.
    End,
}

/// When a stage that batches the objects of a frame (the inference stage,
/// the sampler) runs its batch, so that batches depend on the messages, not
/// on their timing:
///
/// - at the frame's last message: the first without
///   [`flags::MORE_IN_FRAME`] (so a producer that never sets it gets each
///   message handled at once), or when the batch is full;
/// - before holding a message of another frame (the rest of the held
///   frame was lost);
/// - at [`Flush::End`]. An idle input runs nothing: a batch waits for the
///   rest of its frame.
///
/// [`flags::MORE_IN_FRAME`]: poseflow_contracts::flags::MORE_IN_FRAME
#[derive(Debug, Clone)]
pub struct FrameBatches {
    capacity: usize,
    frame: Option<u64>,
}

impl FrameBatches {
    /// Batches of at most `capacity` messages (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self { capacity: capacity.max(1), frame: None }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Before holding a message: whether the held batch (`held` messages)
    /// must run first.
    pub fn run_before(&self, header: &Header, held: usize) -> bool {
        held > 0 && self.frame != Some(header.frame_id)
    }

    /// After holding a message (now `held` in all): whether the batch is
    /// complete.
    pub fn run_after(&mut self, header: &Header, held: usize) -> bool {
        self.frame = Some(header.frame_id);
        header.flags & poseflow_contracts::flags::MORE_IN_FRAME == 0 || held >= self.capacity
    }

    /// At a flush: whether to run what is held.
    pub fn run_at(&self, reason: Flush) -> bool {
        reason == Flush::End
    }

    /// What handling one message returns: `before` is the held batch's
    /// result when the message ran it first, `this` the message's own (it
    /// is handled whatever `before` gave, never dropped with it). The first
    /// failure goes to the runtime, which counts it; a second is added to
    /// `rejected` ([`Transform::take_rejected`]).
    pub fn first_failure<E>(before: Result<(), E>, this: Result<(), E>, rejected: &mut u64) -> Result<(), E> {
        if before.is_err() && this.is_err() {
            *rejected += 1;
        }
        before.and(this)
    }
}

/// A stage with one input and one output edge.
pub trait Transform {
    type In: MessageHeader;
    type Out: MessageHeader;
    type Error: std::error::Error;

    /// The timestamp slot this stage writes on its outputs, if any.
    const SLOT: Option<StampSlot>;

    /// Handles one input; may emit zero or more outputs.
    fn process(&mut self, input: Input<'_, Self::In>, output: &mut dyn Emitter<Self::Out>) -> Result<(), Self::Error>;

    /// Called when the input queue has run empty after one or more inputs
    /// were processed, before the stage waits for more ([`Flush::Idle`]),
    /// and once when the input has ended or the stage stops
    /// ([`Flush::End`]). A stage that batches keeps inputs in `process` and
    /// runs them together when a batch is complete (see [`FrameBatches`]),
    /// or here; at `End` it must run whatever it holds. The default holds
    /// nothing.
    fn flush(&mut self, output: &mut dyn Emitter<Self::Out>, reason: Flush) -> Result<(), Self::Error> {
        let _ = (output, reason);
        Ok(())
    }

    /// As [`Source::take_rejected`]: parts of inputs rejected since the
    /// last call without failing the whole input.
    fn take_rejected(&mut self) -> u64 {
        0
    }
}

/// A [`Transform`] that also answers requests on one request-response edge:
/// the inference stage turns each Observation into a cached condition (its
/// output is the handle) and answers the sampler's velocity requests from
/// that cache.
pub trait Server: Transform {
    type Request: MessageHeader;
    type Response: MessageHeader;

    /// Answers one request with exactly one `reply.emit`. A request that
    /// cannot be served still gets a response (an error status in its
    /// header), so the caller never waits for a timeout; `Err` is for a reply
    /// that could not be sent.
    fn answer(
        &mut self,
        request: Input<'_, Self::Request>,
        reply: &mut dyn Emitter<Self::Response>,
    ) -> Result<(), Self::Error>;

    /// Answers a request whose payload breaks its contract (the runtime has
    /// counted and logged it) with an error status.
    fn answer_invalid(
        &mut self,
        request: &Self::Request,
        reply: &mut dyn Emitter<Self::Response>,
    ) -> Result<(), Self::Error>;
}

/// A [`Transform`] that also reads a side input (graph key `side_inputs`):
/// messages it keeps for the inputs that need them. The selector keeps each
/// Observation's points until that object's Hypotheses arrive; a tracking
/// sampler keeps the last Estimate of each object. Side messages published
/// before an input are handed over before that input.
pub trait Joined: Transform {
    type Side: MessageHeader;

    fn side(&mut self, input: Input<'_, Self::Side>) -> Result<(), Self::Error>;

    /// Whether the stage waits for a side message before it is handed
    /// `next`, and for how long at most; `None` (the default) never waits.
    /// The runtime reads the side input meanwhile and asks again, so the
    /// wait ends as soon as the message has come. The tracking sampler
    /// waits for the estimate of the frame before when the next frame of
    /// its object would otherwise start from the prior.
    fn awaits_side(&self, next: &Self::In) -> Option<Duration> {
        let _ = next;
        None
    }
}

/// How often a stage waiting for a side message ([`Joined::awaits_side`])
/// looks again: a tenth of a millisecond added to an estimate's way back.
const SIDE_POLL: Duration = Duration::from_micros(100);

/// Reads the side input (`read_side`) until `stage` no longer awaits a side
/// message before `next` or the longest wait it asked for has passed.
/// Returns whether it gave up waiting.
pub(crate) fn await_side<J: Joined>(stage: &mut J, next: &J::In, mut read_side: impl FnMut(&mut J)) -> bool {
    let started = std::time::Instant::now();
    loop {
        read_side(stage);
        match stage.awaits_side(next) {
            None => return false,
            Some(longest) if started.elapsed() >= longest => return true,
            Some(_) => std::thread::sleep(SIDE_POLL),
        }
    }
}

/// What a source did on one call.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceStep {
    /// It may be called again.
    Continue,
    /// The stream is over (end of a dataset or recording).
    Finished,
    /// Nothing came within a short wait (a live camera between images); it
    /// may be called again. Not counted as work.
    Idle,
}

/// A stage with no input: a camera, a dataset reader, a replay.
pub trait Source {
    type Out: MessageHeader;
    type Error: std::error::Error;

    const SLOT: Option<StampSlot>;

    /// Emits the next message(s).
    fn next(&mut self, output: &mut dyn Emitter<Self::Out>) -> Result<SourceStep, Self::Error>;

    /// Inputs rejected since the last call without failing the step (a bad
    /// object in an otherwise good frame); the runtime adds them to the
    /// stage's error count in its heartbeats.
    fn take_rejected(&mut self) -> u64 {
        0
    }
}

/// A stage with no output: a robot interface, a recorder, a checker.
pub trait Sink {
    type In: MessageHeader;
    type Error: std::error::Error;

    fn consume(&mut self, input: Input<'_, Self::In>) -> Result<(), Self::Error>;

    /// Called once after the stream ended or the stage was asked to stop.
    fn finish(&mut self) -> Result<(), Self::Error>;
}

#[cfg(test)]
mod tests {
    use poseflow_contracts::flags::MORE_IN_FRAME;

    use super::*;

    fn header(frame: u64, flags: u32) -> Header {
        Header { flags, ..Header::new(frame, 1) }
    }

    /// Messages marked `MORE_IN_FRAME` wait for their frame's last one; an
    /// unmarked message, a full batch or a message of the next frame runs
    /// the batch; an idle input runs nothing, the end everything.
    #[test]
    fn frame_batches_follow_the_messages() {
        let mut batches = FrameBatches::new(8);
        assert!(!batches.run_before(&header(3, MORE_IN_FRAME), 0));
        assert!(!batches.run_after(&header(3, MORE_IN_FRAME), 1));
        assert!(!batches.run_at(Flush::Idle) && batches.run_at(Flush::End));
        assert!(!batches.run_before(&header(3, 0), 1));
        assert!(batches.run_after(&header(3, 0), 2), "the frame's last");
        assert!(!batches.run_after(&header(4, MORE_IN_FRAME), 1));
        assert!(batches.run_before(&header(5, 0), 1), "the rest of frame 4 was lost: its batch runs before frame 5");
        assert!(batches.run_after(&header(6, 0), 1), "an unmarked message is handled at once");
        let mut small = FrameBatches::new(2);
        assert!(!small.run_after(&header(1, MORE_IN_FRAME), 1));
        assert!(small.run_after(&header(1, MORE_IN_FRAME), 2), "full");
        assert_eq!(FrameBatches::new(0).capacity(), 1);
    }

    /// The first failure is returned; only a second is counted as rejected.
    #[test]
    fn a_batch_and_its_message_report_each_failure_once() {
        let mut rejected = 0;
        assert_eq!(FrameBatches::first_failure::<u8>(Ok(()), Ok(()), &mut rejected), Ok(()));
        assert_eq!(FrameBatches::first_failure(Err(1), Ok(()), &mut rejected), Err(1));
        assert_eq!(FrameBatches::first_failure(Ok(()), Err(2), &mut rejected), Err(2));
        assert_eq!(rejected, 0);
        assert_eq!(FrameBatches::first_failure(Err(1), Err(2), &mut rejected), Err(1));
        assert_eq!(rejected, 1);
    }
}
