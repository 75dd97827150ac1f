//! Which timestamp slot a stage writes: the graph's `stamp` key.

use poseflow_contracts::StampSlot;
use serde::{Deserialize, Serialize};

/// A stage entry's `stamp`: a slot of the message header's stamps, or none.
/// A stage without the key writes its registration's default slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Stamp {
    Slot(StampSlot),
    /// The stage stamps nothing (a pass-through measured by its neighbours).
    Off,
}

impl Stamp {
    /// What graph files may write, for error messages.
    pub fn expected() -> String {
        let names: Vec<&str> = StampSlot::ALL.iter().map(|s| s.name()).collect();
        format!("a timestamp slot ({}) or \"none\"", names.join(", "))
    }

    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "none" => Some(Self::Off),
            name => StampSlot::from_name(name).map(Self::Slot),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Slot(slot) => slot.name(),
            Self::Off => "none",
        }
    }

    /// The slot a stage writes: the graph's choice, else `default` (its
    /// registration's).
    pub fn resolve(choice: Option<Stamp>, default: Option<StampSlot>) -> Option<StampSlot> {
        match choice {
            Some(Self::Slot(slot)) => Some(slot),
            Some(Self::Off) => None,
            None => default,
        }
    }
}

impl TryFrom<String> for Stamp {
    type Error = String;

    fn try_from(text: String) -> Result<Self, String> {
        Self::parse(&text).ok_or_else(|| format!("expected {}, found {text:?}", Self::expected()))
    }
}

impl From<Stamp> for String {
    fn from(stamp: Stamp) -> String {
        stamp.name().to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_slot_and_none_round_trip_through_their_names() {
        for slot in StampSlot::ALL {
            assert_eq!(Stamp::parse(slot.name()), Some(Stamp::Slot(slot)));
        }
        assert_eq!(Stamp::parse("none"), Some(Stamp::Off));
        assert_eq!(Stamp::parse("Ingest"), None);
        let error = Stamp::try_from("detector".to_owned()).unwrap_err();
        assert!(error.contains("next_view") && error.contains("\"detector\""), "{error}");
    }

    #[test]
    fn the_graph_choice_overrides_the_registration_default() {
        let default = Some(StampSlot::Sampler);
        assert_eq!(Stamp::resolve(None, default), default);
        assert_eq!(Stamp::resolve(Some(Stamp::Off), default), None);
        assert_eq!(Stamp::resolve(Some(Stamp::Slot(StampSlot::Grasp)), default), Some(StampSlot::Grasp));
        assert_eq!(Stamp::resolve(Some(Stamp::Slot(StampSlot::Grasp)), None), Some(StampSlot::Grasp));
    }
}
