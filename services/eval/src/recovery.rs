//! Recovery after a video's events (`video_events.json`): how many images
//! after an object reappears (an occlusion) or moves (a teleport) its
//! estimate is back within 10°5cm.

use std::collections::BTreeMap;

use poseflow_scene::video::EventRecord;
use serde::Serialize;

/// An occluded object counts as visible again from the first image, after
/// it was less visible, in which this share of its silhouette shows.
pub const REAPPEARED_VISIBLE: f64 = 0.3;
/// Images after reappearing within which a recovery counts as prompt.
pub const PROMPT_IMAGES: u32 = 2;

/// One event's outcome.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EventOutcome {
    pub obj_id: u32,
    pub kind: &'static str,
    /// The image the object was visible again from (occlusion), or the
    /// first image from its move on in which it was visible (teleport);
    /// `None` when it was not visible again within the video, or an
    /// occluded object was never hidden below the threshold.
    pub reappeared: Option<u32>,
    /// Images from `reappeared` to the first estimate within 10°5cm; `None`
    /// when none came before the video ended.
    pub recovered_after: Option<u32>,
}

impl EventOutcome {
    pub fn prompt(&self) -> bool {
        self.recovered_after.is_some_and(|images| images <= PROMPT_IMAGES)
    }
}

/// The outcome of each event. `visible` gives an object's visible share
/// per (image, object id); `within` whether the estimate of (image, object
/// id) was within 10°5cm (absent: no estimate, a miss); `frames` is the
/// video's length.
pub fn outcomes(
    events: &[EventRecord],
    visible: &BTreeMap<(u32, u32), f64>,
    within: &BTreeMap<(u32, u32), bool>,
    frames: u32,
) -> Vec<EventOutcome> {
    events
        .iter()
        .map(|event| {
            let (obj_id, kind, reappeared) = match *event {
                EventRecord::Occlusion { obj_id, start, .. } => {
                    let shown = |im: u32| visible.get(&(im, obj_id)).copied().unwrap_or(0.0);
                    let hidden = (start..frames).find(|&im| shown(im) < REAPPEARED_VISIBLE);
                    let back = hidden.and_then(|h| (h..frames).find(|&im| shown(im) >= REAPPEARED_VISIBLE));
                    (obj_id, "occlusion", back)
                }
                // An object moved while out of sight (beyond the image's
                // edge, behind another) can only be found once it shows.
                EventRecord::Teleport { obj_id, at, .. } => {
                    let shown = |im: u32| visible.get(&(im, obj_id)).copied().unwrap_or(0.0);
                    (obj_id, "teleport", (at..frames).find(|&im| shown(im) >= REAPPEARED_VISIBLE))
                }
            };
            let recovered_after = reappeared.and_then(|from| {
                (from..frames).find(|&im| within.get(&(im, obj_id)).copied().unwrap_or(false)).map(|im| im - from)
            });
            EventOutcome { obj_id, kind, reappeared, recovered_after }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovery_counts_from_reappearance_and_from_the_teleport_once_visible() {
        let events = [
            EventRecord::Occlusion { obj_id: 1, start: 2, end: 9, hidden: 3 },
            EventRecord::Teleport { obj_id: 5, at: 4, turn_deg: 120.0, shift_m: [0.0, 0.01] },
            EventRecord::Occlusion { obj_id: 5, start: 10, end: 12, hidden: 1 },
            EventRecord::Teleport { obj_id: 7, at: 2, turn_deg: 90.0, shift_m: [0.0, 0.0] },
        ];
        // Object 1: fully visible, hidden in images 4-6, 0.2 visible in 7,
        // 0.5 in 8; object 5 always visible; object 7 out of sight until
        // image 6.
        let mut visible = BTreeMap::new();
        for im in 0..14 {
            let one = match im {
                4..=6 => 0.0,
                7 => 0.2,
                8 => 0.5,
                _ => 1.0,
            };
            visible.insert((im, 1), one);
            visible.insert((im, 5), 1.0);
            visible.insert((im, 7), if im < 6 { 0.0 } else { 1.0 });
        }
        let mut within = BTreeMap::new();
        for im in 0..14 {
            within.insert((im, 1), !(4..=8).contains(&im));
            within.insert((im, 5), !(4..=6).contains(&im));
            within.insert((im, 7), im >= 7);
        }
        let outcomes = outcomes(&events, &visible, &within, 14);
        assert_eq!((outcomes[0].reappeared, outcomes[0].recovered_after), (Some(8), Some(1)));
        assert!(outcomes[0].prompt());
        assert_eq!((outcomes[1].reappeared, outcomes[1].recovered_after), (Some(4), Some(3)));
        assert!(!outcomes[1].prompt());
        // Never hidden below the threshold: nothing to recover from.
        assert_eq!((outcomes[2].reappeared, outcomes[2].recovered_after), (None, None));
        // Moved while out of sight: counted from when it shows.
        assert_eq!((outcomes[3].reappeared, outcomes[3].recovered_after), (Some(6), Some(1)));
        // Never back within the video.
        within.retain(|&(im, obj), _| obj != 1 || im < 4);
        assert_eq!(super::outcomes(&events[..1], &visible, &within, 14)[0].recovered_after, None);
    }
}
