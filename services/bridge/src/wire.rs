//! How one edge's traffic travels in a Zenoh sample.
//!
//! ```text
//! "PFZ"           3 bytes magic
//! version         u8 (1)
//! kind            u8: 0 a message, 1 the end of the stream
//! for a message:
//!   header_len    u32 little-endian
//!   header        the contract header's raw #[repr(C)] bytes
//!   payload       f32 little-endian, to the end of the sample
//! ```
//!
//! Contract headers are sent as their in-memory bytes, as recordings store
//! them, so both hosts must be little-endian (x86-64 and aarch64 Linux
//! are); the receiving bridge checks the header's size against its type
//! and the payload against the header's counts before publishing.

pub const MAGIC: &[u8; 3] = b"PFZ";
pub const VERSION: u8 = 1;
const KIND_MESSAGE: u8 = 0;
const KIND_END: u8 = 1;
const PREAMBLE: usize = MAGIC.len() + 2;

/// A decoded sample.
#[derive(Debug, Clone, PartialEq)]
pub enum WireMessage<'a> {
    Message { header: &'a [u8], payload: Vec<f32> },
    EndOfStream,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    #[error("not a PoseFlow bridge sample (expected the magic \"PFZ\" and version {VERSION}, found {found:?})")]
    Preamble { found: Vec<u8> },
    #[error("unknown sample kind {0} (expected 0, a message, or 1, the end of the stream)")]
    Kind(u8),
    #[error("sample of {len} bytes is too short for its {what}")]
    Truncated { len: usize, what: &'static str },
    #[error("payload of {0} bytes is not a whole number of f32 values")]
    Payload(usize),
}

/// A message as a sample's bytes.
pub fn encode_message(header: &[u8], payload: &[f32]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(PREAMBLE + 4 + header.len() + 4 * payload.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[VERSION, KIND_MESSAGE]);
    bytes.extend_from_slice(&(header.len() as u32).to_le_bytes());
    bytes.extend_from_slice(header);
    let start = bytes.len();
    // Sized first, then written in place: a loop the compiler turns into a copy.
    bytes.resize(start + 4 * payload.len(), 0);
    for (out, value) in bytes[start..].chunks_exact_mut(4).zip(payload) {
        out.copy_from_slice(&value.to_le_bytes());
    }
    bytes
}

/// The end-of-stream marker's bytes.
pub fn encode_end() -> Vec<u8> {
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&[VERSION, KIND_END]);
    bytes
}

pub fn decode(bytes: &[u8]) -> Result<WireMessage<'_>, WireError> {
    if bytes.len() < PREAMBLE || &bytes[..3] != MAGIC || bytes[3] != VERSION {
        return Err(WireError::Preamble { found: bytes[..bytes.len().min(PREAMBLE)].to_vec() });
    }
    match bytes[4] {
        KIND_END => Ok(WireMessage::EndOfStream),
        KIND_MESSAGE => {
            let rest = &bytes[PREAMBLE..];
            let truncated = |what| WireError::Truncated { len: bytes.len(), what };
            let len_bytes: [u8; 4] = rest.get(..4).ok_or(truncated("header length"))?.try_into().expect("4 bytes");
            let header_len = u32::from_le_bytes(len_bytes) as usize;
            let header = rest.get(4..4 + header_len).ok_or(truncated("header"))?;
            let payload = &rest[4 + header_len..];
            if !payload.len().is_multiple_of(4) {
                return Err(WireError::Payload(payload.len()));
            }
            let mut values = vec![0.0f32; payload.len() / 4];
            for (value, bytes) in values.iter_mut().zip(payload.chunks_exact(4)) {
                *value = f32::from_le_bytes(bytes.try_into().expect("4 bytes"));
            }
            let payload = values;
            Ok(WireMessage::Message { header, payload })
        }
        kind => Err(WireError::Kind(kind)),
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    #[test]
    fn the_layout_is_the_documented_one() {
        let bytes = encode_message(&[7, 8], &[1.0]);
        assert_eq!(bytes, [b'P', b'F', b'Z', 1, 0, 2, 0, 0, 0, 7, 8, 0, 0, 0x80, 0x3f]);
        assert_eq!(encode_end(), [b'P', b'F', b'Z', 1, 1]);
        assert_eq!(decode(&encode_end()), Ok(WireMessage::EndOfStream));
    }

    #[test]
    fn damaged_samples_are_named() {
        assert!(matches!(decode(b"XYZ\x01\x00"), Err(WireError::Preamble { .. })));
        assert!(matches!(decode(b"PFZ\x02\x00"), Err(WireError::Preamble { .. })));
        assert!(matches!(decode(b"PF"), Err(WireError::Preamble { .. })));
        assert_eq!(decode(b"PFZ\x01\x07"), Err(WireError::Kind(7)));
        assert_eq!(decode(b"PFZ\x01\x00\x01"), Err(WireError::Truncated { len: 6, what: "header length" }));
        assert_eq!(decode(b"PFZ\x01\x00\x09\x00\x00\x00ab"), Err(WireError::Truncated { len: 11, what: "header" }));
        assert_eq!(decode(b"PFZ\x01\x00\x00\x00\x00\x00abc"), Err(WireError::Payload(3)));
    }

    proptest! {
        /// Every message comes back bit for bit, NaN payloads included.
        #[test]
        fn messages_round_trip(header in proptest::collection::vec(any::<u8>(), 0..200),
                               bits in proptest::collection::vec(any::<u32>(), 0..300)) {
            let payload: Vec<f32> = bits.iter().map(|b| f32::from_bits(*b)).collect();
            let bytes = encode_message(&header, &payload);
            let WireMessage::Message { header: decoded_header, payload: decoded } = decode(&bytes).unwrap() else {
                panic!("not a message");
            };
            prop_assert_eq!(decoded_header, &header[..]);
            prop_assert_eq!(decoded.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), bits);
        }

        /// Arbitrary bytes decode or fail; they never panic.
        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = decode(&bytes);
        }
    }
}
