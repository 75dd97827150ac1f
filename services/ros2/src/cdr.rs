//! OMG CDR (XCDR1, little-endian), the encoding of ROS 2 messages on the
//! wire: a 4-byte encapsulation header (`00 01 00 00`, CDR_LE), then each
//! field in declaration order. A primitive is aligned to its own size,
//! counted from the end of the encapsulation header; a string is a `u32`
//! length including its NUL, the bytes and the NUL; a sequence is a `u32`
//! count then its elements; a fixed array is its elements only.

/// The encapsulation header of little-endian plain CDR.
pub const CDR_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
/// Big-endian plain CDR, which other writers may use.
const CDR_BE: [u8; 4] = [0x00, 0x00, 0x00, 0x00];

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CdrError {
    #[error("{field}: the message ends at byte {len}, {needed} bytes short")]
    Truncated { field: &'static str, len: usize, needed: usize },
    #[error("encapsulation header {found:02x?}: expected {CDR_LE:02x?} (little-endian CDR)")]
    Encapsulation { found: Vec<u8> },
    #[error("{field}: {detail}")]
    Invalid { field: &'static str, detail: String },
}

/// Writes one message.
#[derive(Debug, Clone)]
pub struct CdrWriter {
    bytes: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        Self { bytes: CDR_LE.to_vec() }
    }

    fn align(&mut self, size: usize) {
        let offset = self.bytes.len() - CDR_LE.len();
        let padding = (size - offset % size) % size;
        self.bytes.extend(std::iter::repeat_n(0, padding));
    }

    pub fn u8(&mut self, value: u8) {
        self.bytes.push(value);
    }

    pub fn i32(&mut self, value: i32) {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn u32(&mut self, value: u32) {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn f64(&mut self, value: f64) {
        self.align(8);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn string(&mut self, value: &str) {
        self.u32(value.len() as u32 + 1);
        self.bytes.extend_from_slice(value.as_bytes());
        self.bytes.push(0);
    }

    /// A sequence's element count (`u32`), before its elements.
    pub fn count(&mut self, count: usize) {
        self.u32(count as u32);
    }

    /// `uint8[]`.
    pub fn byte_sequence(&mut self, values: &[u8]) {
        self.count(values.len());
        self.bytes.extend_from_slice(values);
    }

    pub fn finish(self) -> Vec<u8> {
        self.bytes
    }
}

/// Reads one message, field by field; every read names its field when the
/// message is too short.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    body: &'a [u8],
    at: usize,
    big_endian: bool,
}

impl<'a> CdrReader<'a> {
    pub fn new(bytes: &'a [u8]) -> Result<Self, CdrError> {
        let header = bytes.get(..4).ok_or(CdrError::Encapsulation { found: bytes.to_vec() })?;
        let big_endian = if header[..2] == CDR_LE[..2] {
            false
        } else if header[..2] == CDR_BE[..2] {
            true
        } else {
            return Err(CdrError::Encapsulation { found: header.to_vec() });
        };
        Ok(Self { body: &bytes[4..], at: 0, big_endian })
    }

    fn take(&mut self, field: &'static str, size: usize, align: usize) -> Result<&'a [u8], CdrError> {
        let start = self.at.next_multiple_of(align);
        let end = start.checked_add(size).filter(|end| *end <= self.body.len()).ok_or(CdrError::Truncated {
            field,
            len: self.body.len() + 4,
            needed: (start + size).saturating_sub(self.body.len()),
        })?;
        self.at = end;
        Ok(&self.body[start..end])
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], CdrError> {
        let mut bytes: [u8; N] = self.take(field, N, N)?.try_into().expect("take returns N bytes");
        if self.big_endian {
            bytes.reverse();
        }
        Ok(bytes)
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(field, 1, 1)?[0])
    }

    pub fn i32(&mut self, field: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array(field)?))
    }

    pub fn u32(&mut self, field: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }

    pub fn f64(&mut self, field: &'static str) -> Result<f64, CdrError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }

    pub fn string(&mut self, field: &'static str) -> Result<String, CdrError> {
        let len = self.u32(field)? as usize;
        let bytes = self.take(field, len, 1)?;
        let text = bytes
            .strip_suffix(&[0])
            .ok_or_else(|| CdrError::Invalid { field, detail: "a string without its terminating NUL".into() })?;
        String::from_utf8(text.to_vec()).map_err(|err| CdrError::Invalid { field, detail: err.to_string() })
    }

    /// A sequence's element count, checked against the bytes left at
    /// `element_size` bytes or more per element.
    pub fn count(&mut self, field: &'static str, element_size: usize) -> Result<usize, CdrError> {
        let count = self.u32(field)? as usize;
        let left = self.body.len() - self.at;
        if count.saturating_mul(element_size) > left {
            return Err(CdrError::Truncated { field, len: self.body.len() + 4, needed: count * element_size - left });
        }
        Ok(count)
    }

    /// `uint8[]`, borrowed from the message.
    pub fn byte_sequence(&mut self, field: &'static str) -> Result<&'a [u8], CdrError> {
        let len = self.count(field, 1)?;
        self.take(field, len, 1)
    }

    pub fn f64_sequence(&mut self, field: &'static str) -> Result<Vec<f64>, CdrError> {
        let count = self.count(field, 8)?;
        (0..count).map(|_| self.f64(field)).collect()
    }

    pub fn f64_array<const N: usize>(&mut self, field: &'static str) -> Result<[f64; N], CdrError> {
        let mut values = [0.0; N];
        for value in &mut values {
            *value = self.f64(field)?;
        }
        Ok(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_aligned_from_the_end_of_the_encapsulation_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.u8(1);
        w.u32(9);
        let bytes = w.finish();
        // header 4 | u8 at 0 | pad to 8 | f64 8..16 | len 16..20 | "ab\0" 20..23 | u8 23 | u32 24..28
        assert_eq!(bytes.len(), 4 + 28);
        assert_eq!(&bytes[..4], &CDR_LE);
        assert_eq!(&bytes[4 + 16..4 + 23], &[3, 0, 0, 0, b'a', b'b', 0]);
        let mut r = CdrReader::new(&bytes).unwrap();
        assert_eq!(r.u8("a").unwrap(), 7);
        assert_eq!(r.f64("b").unwrap(), 1.5);
        assert_eq!(r.string("c").unwrap(), "ab");
        assert_eq!(r.u8("d").unwrap(), 1);
        assert_eq!(r.u32("e").unwrap(), 9);
        assert!(matches!(r.u8("after"), Err(CdrError::Truncated { field: "after", .. })));
    }

    #[test]
    fn big_endian_messages_read_and_bad_headers_are_named() {
        let bytes = [0, 0, 0, 0, 0, 0, 1, 2];
        assert_eq!(CdrReader::new(&bytes).unwrap().u32("x").unwrap(), 258);
        let err = CdrReader::new(&[0, 7, 0, 0]).unwrap_err().to_string();
        assert!(err.contains("encapsulation") && err.contains("little-endian"), "{err}");
        assert!(CdrReader::new(&[0]).is_err());
    }

    #[test]
    fn a_sequence_longer_than_the_message_is_refused_before_allocating() {
        let mut w = CdrWriter::new();
        w.u32(u32::MAX);
        let err = CdrReader::new(&w.finish()).unwrap().f64_sequence("d").unwrap_err();
        assert!(matches!(err, CdrError::Truncated { field: "d", .. }), "{err}");
    }
}
