//! Service names: `poseflow/<graph instance>/<edge>`.

use crate::TransportError;

/// Graph instance and edge names: ASCII letters, digits, `-` and `_`, 1 to
/// 64 characters, so they are safe in service names and file names alike.
pub fn validate_name(kind: &'static str, name: &str) -> Result<(), TransportError> {
    let ok =
        !name.is_empty() && name.len() <= 64 && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if ok {
        Ok(())
    } else {
        Err(TransportError::Name {
            name: name.to_string(),
            detail: format!("a {kind} name must be 1-64 characters of A-Z, a-z, 0-9, '-' or '_'"),
        })
    }
}

pub fn edge_service_name(instance: &str, edge: &str) -> Result<String, TransportError> {
    validate_name("graph instance", instance)?;
    validate_name("edge", edge)?;
    Ok(format!("poseflow/{instance}/{edge}"))
}

/// The service on which stage `stage` of graph `instance` publishes its
/// heartbeat.
pub fn heartbeat_service_name(instance: &str, stage: &str) -> Result<String, TransportError> {
    validate_name("graph instance", instance)?;
    validate_name("stage", stage)?;
    Ok(format!("poseflow/{instance}/_heartbeat/{stage}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_namespaced_and_checked() {
        assert_eq!(edge_service_name("g1", "hypotheses").unwrap(), "poseflow/g1/hypotheses");
        assert!(edge_service_name("g/1", "x").is_err());
        assert!(edge_service_name("g", "").is_err());
        let err = edge_service_name("g", "a b").unwrap_err().to_string();
        assert!(err.contains("\"a b\"") && err.contains("edge name"), "{err}");
    }
}
