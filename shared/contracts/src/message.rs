//! What every message type shares: the [`Header`], an `f32` payload whose
//! length the header determines, and the check that the two agree.

use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::{ContractError, Header};

/// `f32` values of one pose: `R` row-major (9), then `t` (3); metres.
pub const POSE_LEN: usize = 12;
/// `f32` values of one velocity: `v` (3), then body-frame `ω` (3).
pub const VELOCITY_LEN: usize = 6;

/// Upper bounds that reject garbage headers before any arithmetic on them.
pub mod limits {
    pub const MAX_IMAGE_SIZE: u32 = 1024;
    pub const MAX_POINTS: u32 = 65_536;
    pub const MAX_DEPTH_GRID: u32 = 256;
    pub const MAX_SAMPLES: u32 = 4096;
    pub const MAX_MODES: u32 = 64;
    pub const MAX_GRASPS: u32 = 4096;
    pub const MAX_CANDIDATES: u32 = 4096;
    pub const MAX_FRAME_SIDE: u32 = 8192;
    pub const MAX_DETECTIONS: u32 = 256;
}

/// A message's user header (the fixed-size part); the tensors travel beside
/// it as a flat `f32` slice.
pub trait MessageHeader: ZeroCopySend + Copy + Default + std::fmt::Debug {
    /// Name used in errors and logs.
    const NAME: &'static str;

    fn header(&self) -> &Header;
    fn header_mut(&mut self) -> &mut Header;

    /// The number of `f32` values the payload must hold, after checking every
    /// count in the header against its limit.
    fn payload_len(&self) -> Result<usize, ContractError>;

    /// Checks that `payload` is exactly as long as the header announces.
    fn check_payload(&self, payload: &[f32]) -> Result<(), ContractError> {
        let expected = self.payload_len()?;
        if payload.len() == expected {
            Ok(())
        } else {
            Err(ContractError::PayloadLength { message: Self::NAME, expected, actual: payload.len() })
        }
    }
}

/// The `header`/`header_mut` accessors of a contract header whose common
/// [`Header`] is its field `header`.
macro_rules! header_accessors {
    () => {
        fn header(&self) -> &$crate::Header {
            &self.header
        }

        fn header_mut(&mut self) -> &mut $crate::Header {
            &mut self.header
        }
    };
}
pub(crate) use header_accessors;

/// Checks `min <= value <= max` and widens to `usize`.
pub(crate) fn bounded(
    message: &'static str,
    field: &'static str,
    value: u32,
    min: u32,
    max: u32,
    expected: &'static str,
) -> Result<usize, ContractError> {
    if (min..=max).contains(&value) {
        Ok(value as usize)
    } else {
        Err(ContractError::FieldOutOfRange { message, field, value: u64::from(value), expected })
    }
}

/// Splits `payload` into consecutive sections of the given lengths. Callers
/// have checked the total length with [`MessageHeader::check_payload`].
pub(crate) fn sections<const N: usize>(payload: &[f32], lengths: [usize; N]) -> [&[f32]; N] {
    let mut rest = payload;
    lengths.map(|len| {
        let (head, tail) = rest.split_at(len);
        rest = tail;
        head
    })
}
