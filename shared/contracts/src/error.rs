/// A message whose header and payload disagree, or whose header holds a
/// value outside the contract. Messages name the message type, the field and
/// what was expected, so a plug-in author can find the bug on their side.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ContractError {
    #[error("{message}: payload holds {actual} f32 values, the header announces {expected}")]
    PayloadLength { message: &'static str, expected: usize, actual: usize },

    #[error("{message}: field `{field}` = {value}: expected {expected}")]
    FieldOutOfRange { message: &'static str, field: &'static str, value: u64, expected: &'static str },

    #[error("{message}: field `{field}` = {value}: expected {expected}")]
    InvalidField { message: &'static str, field: &'static str, value: String, expected: &'static str },
}
