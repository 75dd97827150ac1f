//! Pairing a camera's streams by stamp: colour, aligned depth and, when
//! configured, a label image arrive as separate topics; a frame is one
//! message of each whose stamps agree within a tolerance.
//!
//! Each stream keeps at most `capacity` messages; a message that can no
//! longer be paired (older than a pair already made, or than anything the
//! other streams can still deliver) or that falls out of a full queue is
//! counted as unpaired, never dropped in silence. Stamps are assumed to
//! increase within each stream, as a driver publishes them.

use std::collections::VecDeque;

/// A message with the stamp it is paired by (ns).
pub trait Stamped {
    fn stamp_ns(&self) -> u64;
}

/// The pairing of `N`-stream frames; stream 0 leads (colour).
#[derive(Debug)]
pub struct Pairing<T> {
    tolerance_ns: u64,
    capacity: usize,
    queues: Vec<VecDeque<T>>,
    unpaired: Vec<u64>,
}

impl<T: Stamped> Pairing<T> {
    pub fn new(streams: usize, tolerance_ns: u64, capacity: usize) -> Self {
        Self {
            tolerance_ns,
            capacity: capacity.max(1),
            queues: (0..streams).map(|_| VecDeque::new()).collect(),
            unpaired: vec![0; streams],
        }
    }

    /// Messages of each stream counted as unpaired so far.
    pub fn unpaired(&self) -> &[u64] {
        &self.unpaired
    }

    /// Messages waiting to be paired.
    pub fn waiting(&self) -> usize {
        self.queues.iter().map(VecDeque::len).sum()
    }

    /// Adds a message of `stream`; the frame it completes, if any (one
    /// message per stream, in stream order).
    pub fn push(&mut self, stream: usize, message: T) -> Option<Vec<T>> {
        let queue = &mut self.queues[stream];
        if queue.len() == self.capacity {
            queue.pop_front();
            self.unpaired[stream] += 1;
        }
        queue.push_back(message);
        self.pair()
    }

    /// Counts everything still waiting as unpaired (the stream ended).
    pub fn finish(&mut self) {
        for (queue, count) in self.queues.iter_mut().zip(&mut self.unpaired) {
            *count += queue.len() as u64;
            queue.clear();
        }
    }

    fn pair(&mut self) -> Option<Vec<T>> {
        loop {
            let lead = self.queues[0].front()?.stamp_ns();
            let (earliest, latest) = (lead.saturating_sub(self.tolerance_ns), lead + self.tolerance_ns);
            // Messages too old to pair with this lead or any later one.
            for stream in 1..self.queues.len() {
                while self.queues[stream].front().is_some_and(|m| m.stamp_ns() < earliest) {
                    self.queues[stream].pop_front();
                    self.unpaired[stream] += 1;
                }
            }
            let mut picks = Vec::with_capacity(self.queues.len());
            let mut lead_hopeless = false;
            for queue in &self.queues[1..] {
                let nearest = queue
                    .iter()
                    .enumerate()
                    .filter(|(_, m)| m.stamp_ns() <= latest)
                    .min_by_key(|(_, m)| m.stamp_ns().abs_diff(lead))
                    .map(|(i, _)| i);
                match nearest {
                    Some(i) => picks.push(i),
                    // Nothing in range: if the stream is already past the
                    // lead's window, the lead can never pair.
                    None => {
                        lead_hopeless = queue.back().is_some_and(|m| m.stamp_ns() > latest);
                        if !lead_hopeless {
                            return None;
                        }
                        break;
                    }
                }
            }
            if lead_hopeless {
                self.queues[0].pop_front();
                self.unpaired[0] += 1;
                continue;
            }
            let mut frame = Vec::with_capacity(self.queues.len());
            frame.push(self.queues[0].pop_front().expect("the lead is there"));
            for (stream, pick) in (1..self.queues.len()).zip(picks) {
                // What came before the pick can only pair with older leads.
                for _ in 0..pick {
                    self.queues[stream].pop_front();
                    self.unpaired[stream] += 1;
                }
                frame.push(self.queues[stream].pop_front().expect("the pick is there"));
            }
            return Some(frame);
        }
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    #[derive(Debug, Clone, Copy, PartialEq)]
    struct M(u64);
    impl Stamped for M {
        fn stamp_ns(&self) -> u64 {
            self.0
        }
    }

    #[test]
    fn equal_stamps_pair_and_a_missing_depth_image_skips_its_colour() {
        let mut p = Pairing::new(2, 5, 8);
        assert_eq!(p.push(0, M(100)), None);
        assert_eq!(p.push(1, M(102)), Some(vec![M(100), M(102)]));
        // Depth of 133 lost: colour 133 cannot pair once depth 166 came.
        assert_eq!(p.push(0, M(133)), None);
        assert_eq!(p.push(0, M(166)), None);
        assert_eq!(p.push(1, M(166)), Some(vec![M(166), M(166)]));
        assert_eq!(p.unpaired(), [1, 0]);
        assert_eq!(p.waiting(), 0);
    }

    #[test]
    fn a_full_queue_drops_its_oldest_and_counts_it() {
        let mut p = Pairing::new(2, 0, 2);
        for t in [1, 2, 3] {
            assert_eq!(p.push(0, M(t)), None);
        }
        assert_eq!(p.unpaired(), [1, 0]);
        assert_eq!(p.push(1, M(3)), Some(vec![M(3), M(3)]));
        assert_eq!(p.unpaired(), [2, 0], "colour 2 is older than the pair made");
    }

    proptest! {
        /// Every message is paired or counted; pairs agree within the
        /// tolerance and come out in stamp order.
        #[test]
        fn every_message_is_paired_or_counted(
            stamps in proptest::collection::vec((0usize..3, 1u64..40), 1..80),
            tolerance in 0u64..10,
            capacity in 1usize..6,
        ) {
            let mut p = Pairing::new(3, tolerance, capacity);
            let mut clocks = [0u64; 3];
            let (mut pushed, mut paired, mut last) = (0u64, 0u64, None);
            for (stream, step) in stamps {
                clocks[stream] += step;
                pushed += 1;
                if let Some(frame) = p.push(stream, M(clocks[stream])) {
                    paired += 3;
                    let lead = frame[0].0;
                    for m in &frame {
                        prop_assert!(m.0.abs_diff(lead) <= tolerance, "{frame:?}");
                    }
                    prop_assert!(last.is_none_or(|l| l < lead));
                    last = Some(lead);
                }
            }
            p.finish();
            prop_assert_eq!(pushed, paired + p.unpaired().iter().sum::<u64>());
        }
    }
}
