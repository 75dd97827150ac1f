//! The header every message starts with: frame, object, flags and the
//! per-stage timestamps that make latency measurable on real traffic.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

/// Number of timestamp slots in [`StageStamps`].
pub const STAGE_SLOTS: usize = 8;

/// A slot of [`StageStamps`]. The numbering is part of the wire contract.
///
/// Which stage of a graph writes which slot is the graph's choice: a stage
/// entry's `stamp` key names the slot (or `none`), and a stage without one
/// writes its registration's default (the slot its name suggests). So a new
/// stage owns a slot by naming one that no stage on its path writes, and
/// latency breakdowns name each interval by the graph stage that stamped it.
#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum StampSlot {
    /// The frame was captured or read from disk.
    Source = 0,
    Ingest = 1,
    Encode = 2,
    Sampler = 3,
    Selector = 4,
    Grasp = 5,
    NextView = 6,
    /// The final consumer (robot, recorder, benchmark).
    Sink = 7,
}

impl StampSlot {
    pub const ALL: [StampSlot; STAGE_SLOTS] = [
        StampSlot::Source,
        StampSlot::Ingest,
        StampSlot::Encode,
        StampSlot::Sampler,
        StampSlot::Selector,
        StampSlot::Grasp,
        StampSlot::NextView,
        StampSlot::Sink,
    ];

    /// The slot's name in graph files (`stamp = "..."`).
    pub fn name(self) -> &'static str {
        match self {
            StampSlot::Source => "source",
            StampSlot::Ingest => "ingest",
            StampSlot::Encode => "encode",
            StampSlot::Sampler => "sampler",
            StampSlot::Selector => "selector",
            StampSlot::Grasp => "grasp",
            StampSlot::NextView => "next_view",
            StampSlot::Sink => "sink",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|slot| slot.name() == name)
    }
}

/// Nanoseconds since the UNIX epoch ([`stamp_clock_ns`], `CLOCK_REALTIME`)
/// at which each stage published its output for this frame; 0 means the
/// stage has not seen the frame.
///
/// The wall clock rather than a monotonic one, for two reasons: it is the
/// clock ROS 2 stamps messages with, so the `Source` slot of a frame from a
/// ROS 2 camera is the image's own stamp and the poses published for it
/// carry that stamp back; and it is shared by every process on a machine
/// and, through NTP or PTP, across machines, so differences between slots
/// written by different processes (or hosts) are meaningful. A clock step
/// (NTP correcting a large error) can make one interval negative; intervals
/// saturate at 0.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("poseflow/StageStamps/v1")]
pub struct StageStamps {
    pub ns: [u64; STAGE_SLOTS],
}

impl StageStamps {
    /// Writes the current time into `slot`.
    pub fn stamp(&mut self, slot: StampSlot) {
        self.ns[slot as usize] = stamp_clock_ns();
    }

    pub fn get(&self, slot: StampSlot) -> Option<u64> {
        Some(self.ns[slot as usize]).filter(|&ns| ns != 0)
    }

    /// Nanoseconds from `from` to `to`, when both slots were stamped.
    pub fn elapsed_ns(&self, from: StampSlot, to: StampSlot) -> Option<u64> {
        Some(self.get(to)?.saturating_sub(self.get(from)?))
    }
}

/// Bits of [`Header::flags`].
pub mod flags {
    /// The sampler started from the previous frame's estimate (tracking).
    pub const TRACKING: u32 = 1 << 0;
    /// A stage upstream restarted since the previous frame; caches keyed by
    /// earlier frames must not be trusted.
    pub const UPSTREAM_RESTARTED: u32 = 1 << 1;
    /// Fewer valid depth points than requested were observed; points were
    /// resampled with replacement to fill the fixed count.
    pub const POINTS_RESAMPLED: u32 = 1 << 2;
    /// Estimate: the selector's track check found the object lost (the
    /// pose does not explain the observation, or too little of the object
    /// was seen to tell); do not act on it. The tracking sampler starts the
    /// object's next frame from the prior.
    pub const LOST: u32 = 1 << 3;
    /// Estimate: the track check failed softly (a poor fit, a jump, a wide
    /// spread), not yet often enough to declare the object lost. The
    /// tracking sampler draws part of the next frame's samples from the prior.
    pub const UNSURE: u32 = 1 << 4;
    /// Estimate: the first that passed the track check after the object
    /// was lost; tracking resumes from it.
    pub const REINITIALISED: u32 = 1 << 5;
    /// Set by the frame source on the first frame of a sequence (a scene
    /// other than the previous frame's) and forwarded downstream: earlier
    /// frames' estimates belong to another scene, so trackers start afresh.
    pub const SEQUENCE_START: u32 = 1 << 6;
    /// Another message of the same frame follows on this edge: the ingest
    /// stage sets it on every Observation of a frame but the last, and the
    /// stages that copy their input's header pass it on. A stage that
    /// batches the objects of a frame runs the batch at the first message
    /// without it, so batches follow the messages, not their timing (a
    /// graph gives the same results as processes and in-process), and a
    /// producer that never sets it gets every message handled at once.
    pub const MORE_IN_FRAME: u32 = 1 << 7;
    /// Hypotheses and Estimate: no network looked at this frame of the
    /// object. The tracking sampler perturbed the previous estimate of a
    /// held track (between its network passes, `tracking.network_every`)
    /// and the selector's fit to the observed points placed it.
    pub const NETWORK_SKIPPED: u32 = 1 << 8;
}

/// The first 80 bytes of every message header.
///
/// | offset | size | field     | type      |
/// |-------:|-----:|-----------|-----------|
/// | 0      | 8    | frame_id  | u64       |
/// | 8      | 4    | object_id | u32       |
/// | 12     | 4    | flags     | u32 ([`flags`]) |
/// | 16     | 64   | stamps    | [u64; 8] ([`StageStamps`], slots by [`StampSlot`]) |
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("poseflow/Header/v1")]
pub struct Header {
    /// Monotonic per source; gaps mean frames were dropped upstream.
    pub frame_id: u64,
    /// BOP object id (e.g. 1 = LM-O ape).
    pub object_id: u32,
    pub flags: u32,
    pub stamps: StageStamps,
}

impl Header {
    pub fn new(frame_id: u64, object_id: u32) -> Self {
        Self { frame_id, object_id, flags: 0, stamps: StageStamps::default() }
    }

    pub fn has_flag(&self, flag: u32) -> bool {
        self.flags & flag != 0
    }
}

/// The clock of [`StageStamps`]: `CLOCK_REALTIME`, nanoseconds since the
/// UNIX epoch (a ROS 2 `builtin_interfaces/Time` as `sec · 10⁹ + nanosec`).
pub fn stamp_clock_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_REALTIME is always
    // available on Linux, so the call cannot fail.
    unsafe { libc::clock_gettime(libc::CLOCK_REALTIME, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// `CLOCK_MONOTONIC` in nanoseconds: for durations inside one process
/// (liveness, heartbeats), never for message stamps.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC is always
    // available on Linux, so the call cannot fail.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_measure_elapsed_time() {
        let mut stamps = StageStamps::default();
        assert_eq!(stamps.elapsed_ns(StampSlot::Source, StampSlot::Ingest), None);
        stamps.stamp(StampSlot::Source);
        std::thread::sleep(std::time::Duration::from_millis(2));
        stamps.stamp(StampSlot::Ingest);
        let elapsed = stamps.elapsed_ns(StampSlot::Source, StampSlot::Ingest).unwrap();
        assert!(elapsed >= 2_000_000, "{elapsed}");
        assert_eq!(stamps.get(StampSlot::Grasp), None);
    }

    #[test]
    fn stamp_slots_are_distinct_and_named() {
        let names: std::collections::BTreeSet<_> = StampSlot::ALL.iter().map(|s| s.name()).collect();
        assert_eq!(names.len(), STAGE_SLOTS);
        for (i, s) in StampSlot::ALL.iter().enumerate() {
            assert_eq!(*s as usize, i);
            assert_eq!(StampSlot::from_name(s.name()), Some(*s));
        }
        assert_eq!(StampSlot::from_name("detector"), None);
    }
}
