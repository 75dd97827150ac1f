//! Contract headers as raw bytes: how recordings store them and how a
//! fuzzer or a foreign-language stage hands them over.

use crate::MessageHeader;

/// The raw bytes of a contract header.
pub fn header_bytes<H: MessageHeader>(header: &H) -> Vec<u8> {
    // SAFETY: contract headers are `#[repr(C)]` plain integers and floats
    // without padding (their layouts are asserted in poseflow-contracts), so
    // every byte is initialised.
    unsafe { std::slice::from_raw_parts((header as *const H).cast::<u8>(), std::mem::size_of::<H>()) }.to_vec()
}

/// A contract header from its raw bytes; `None` if the length is wrong.
pub fn header_from_bytes<H: MessageHeader>(bytes: &[u8]) -> Option<H> {
    // SAFETY: the length matches and every bit pattern is a valid value of a
    // header made of integers and floats.
    (bytes.len() == std::mem::size_of::<H>()).then(|| unsafe { std::ptr::read_unaligned(bytes.as_ptr().cast::<H>()) })
}
