//! A generic f32 tensor: for plug-ins that exchange raw arrays (detector
//! outputs, features) and for transport benchmarks.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, bounded, header_accessors};
use crate::{ContractError, Header};

/// Largest tensor, in f32 values (256 MiB).
pub const MAX_TENSOR_LEN: u64 = 1 << 26;

/// User header of a Tensor (104 bytes, alignment 8).
///
/// | offset | size | field    | type     | meaning |
/// |-------:|-----:|----------|----------|---------|
/// | 0      | 80   | header   | [`Header`] | |
/// | 80     | 16   | shape    | [u32; 4] | extents, outermost first; entries past `rank` are ignored |
/// | 96     | 4    | rank     | u32      | 1..=4 |
/// | 100    | 4    | reserved | u32      | 0 |
///
/// Payload (`f32`): the product of `shape[..rank]` values, row-major.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("poseflow/Tensor/v1")]
pub struct TensorHeader {
    pub header: Header,
    pub shape: [u32; 4],
    pub rank: u32,
    pub reserved: u32,
}

impl TensorHeader {
    /// A rank-1 tensor of `len` values.
    pub fn vector(header: Header, len: u32) -> Self {
        Self { header, shape: [len, 0, 0, 0], rank: 1, reserved: 0 }
    }
}

impl MessageHeader for TensorHeader {
    const NAME: &'static str = "Tensor";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        let rank = bounded(Self::NAME, "rank", self.rank, 1, 4, "1..=4")?;
        let len = self.shape[..rank]
            .iter()
            .try_fold(1u64, |acc, &d| acc.checked_mul(u64::from(d)).filter(|n| *n <= MAX_TENSOR_LEN));
        match len {
            Some(n) => Ok(n as usize),
            None => Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "shape",
                value: self.shape[..rank].iter().fold(1u64, |acc, &d| acc.saturating_mul(u64::from(d))),
                expected: "a product of extents of at most 2^26 values",
            }),
        }
    }
}
