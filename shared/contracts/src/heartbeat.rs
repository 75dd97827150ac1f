//! Stage → supervisor: liveness and counters, published periodically.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, header_accessors};
use crate::{ContractError, Header};

/// Lifecycle of a stage process, as reported in its heartbeat.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageState {
    Running = 1,
    /// Upstream ended; the stage is draining and forwarding end-of-stream.
    Draining = 2,
    /// The stage finished its stream and is about to exit.
    Finished = 3,
}

impl StageState {
    pub fn from_code(code: u32) -> Option<Self> {
        [Self::Running, Self::Draining, Self::Finished].into_iter().find(|s| *s as u32 == code)
    }
}

/// User header of a Heartbeat (136 bytes, alignment 8). No payload. Counters
/// are cumulative since the process started.
///
/// | offset | size | field          | type | meaning |
/// |-------:|-----:|----------------|------|---------|
/// | 0      | 80   | header         | [`Header`] | `frame_id` = last frame seen, `stamps[0]` = send time |
/// | 80     | 4    | pid            | u32  | process id |
/// | 84     | 4    | state          | u32  | [`StageState`] |
/// | 88     | 8    | frames_in      | u64  | messages received and accepted |
/// | 96     | 8    | frames_out     | u64  | messages published |
/// | 104    | 8    | dropped        | u64  | frames missing upstream (gaps in `frame_id`) |
/// | 112    | 8    | errors         | u64  | messages rejected or failed in `process` |
/// | 120    | 4    | latency_p50_us | u32  | median process time per frame, µs: the stage's busy time from one input frame's first message to the next frame's (inputs, flushes, requests answered), or per step of a source |
/// | 124    | 4    | latency_p99_us | u32  | 99th percentile of the same, µs |
/// | 128    | 4    | busy_us        | u32  | time in the current `process` call, sends excluded (0 when idle); a stage stuck in its own code shows it growing |
/// | 132    | 4    | blocked_us     | u32  | time the current send has waited for a full downstream queue (back-pressure, not a hang) |
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("poseflow/Heartbeat/v1")]
pub struct Heartbeat {
    pub header: Header,
    pub pid: u32,
    pub state: u32,
    pub frames_in: u64,
    pub frames_out: u64,
    pub dropped: u64,
    pub errors: u64,
    pub latency_p50_us: u32,
    pub latency_p99_us: u32,
    pub busy_us: u32,
    pub blocked_us: u32,
}

impl MessageHeader for Heartbeat {
    const NAME: &'static str = "Heartbeat";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        Ok(0)
    }
}
