//! rmw_zenoh's conventions, so that ROS 2 nodes running
//! `RMW_IMPLEMENTATION=rmw_zenoh_cpp` see PoseFlow's topics as ROS topics:
//!
//! - **data**: a topic's messages are put on
//!   `<domain>/<topic without its leading />/<dds type>/<type hash>`, the
//!   payload CDR-encoded, with an attachment of the sequence number (`u64`
//!   LE), the source time (`i64` ns LE) and the publisher's GID (a length
//!   byte, then 16 bytes);
//! - **discovery**: liveliness tokens under `@ros2_lv/<domain>/<zenoh
//!   session id>/…` announce each node (`NN`) and each publisher (`MP`) or
//!   subscription (`MS`), which is what `ros2 node list` and `ros2 topic
//!   list` read. Names in tokens have every `/` replaced by `%`.

use crate::msgs::RosType;

/// The QoS of ROS 2's default profile (reliable, volatile, keep last 10)
/// as rmw_zenoh writes it in liveliness tokens.
pub const DEFAULT_QOS: &str = "::,10:,:,:,,";

/// Bytes of a publisher's GID in the attachment.
pub const GID_LEN: usize = 16;

/// What ROS 2 Humble's rmw_zenoh writes where later releases write a
/// type's RIHS01 hash.
pub const NO_TYPE_HASH: &str = "TypeHashNotSupported";

/// The key expression of `topic`'s messages of type `ty` in ROS domain
/// `domain`; `type_hashes` false for Humble.
pub fn topic_key(domain: u32, topic: &str, ty: &RosType, type_hashes: bool) -> String {
    let hash = if type_hashes { ty.hash } else { NO_TYPE_HASH };
    format!("{domain}/{}/{}/{hash}", topic.trim_start_matches('/'), ty.dds_name)
}

/// A name as liveliness tokens write it: `/` → `%`; the root namespace is `%`.
pub fn mangle(name: &str) -> String {
    if name.is_empty() || name == "/" { "%".to_string() } else { name.replace('/', "%") }
}

/// One node of a Zenoh session, as rmw_zenoh identifies it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RosNode {
    pub domain: u32,
    /// The Zenoh session id.
    pub session: String,
    pub node_id: u32,
    pub namespace: String,
    pub name: String,
    /// Whether types are named with their hash (Jazzy and later) or not
    /// (Humble).
    pub type_hashes: bool,
}

/// What a topic endpoint does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndpointKind {
    Publisher,
    Subscription,
}

impl RosNode {
    /// The node's liveliness token.
    pub fn token(&self) -> String {
        format!(
            "@ros2_lv/{}/{}/{}/{}/NN/%/{}/{}",
            self.domain,
            self.session,
            self.node_id,
            self.node_id,
            mangle(&self.namespace),
            mangle(&self.name)
        )
    }

    /// The liveliness token of endpoint `entity_id` of this node on `topic`.
    pub fn endpoint_token(&self, entity_id: u32, kind: EndpointKind, topic: &str, ty: &RosType) -> String {
        let kind = match kind {
            EndpointKind::Publisher => "MP",
            EndpointKind::Subscription => "MS",
        };
        format!(
            "@ros2_lv/{}/{}/{}/{entity_id}/{kind}/%/{}/{}/{}/{}/{}/{DEFAULT_QOS}",
            self.domain,
            self.session,
            self.node_id,
            mangle(&self.namespace),
            mangle(&self.name),
            mangle(topic),
            ty.dds_name,
            if self.type_hashes { ty.hash } else { NO_TYPE_HASH }
        )
    }
}

/// The attachment rmw_zenoh puts on every message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    pub sequence: u64,
    /// When it was published, ns since the epoch.
    pub source_time_ns: i64,
    pub gid: [u8; GID_LEN],
}

impl Attachment {
    pub fn encode(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(17 + GID_LEN);
        bytes.extend_from_slice(&self.sequence.to_le_bytes());
        bytes.extend_from_slice(&self.source_time_ns.to_le_bytes());
        bytes.push(GID_LEN as u8);
        bytes.extend_from_slice(&self.gid);
        bytes
    }

    /// `None` for bytes that are not an rmw_zenoh attachment.
    pub fn decode(bytes: &[u8]) -> Option<Self> {
        let sequence = u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?);
        let source_time_ns = i64::from_le_bytes(bytes.get(8..16)?.try_into().ok()?);
        let gid = bytes.get(17..17 + usize::from(*bytes.get(16)?))?.try_into().ok()?;
        Some(Self { sequence, source_time_ns, gid })
    }
}

/// A topic name ROS 2 accepts: absolute, segments of letters, digits and
/// `_` that do not start with a digit, no `//`, no trailing `/`.
pub fn check_topic(topic: &str) -> Result<(), String> {
    let body = topic.strip_prefix('/').ok_or("expected an absolute name starting with /")?;
    if body.is_empty() {
        return Err("expected a name after /".into());
    }
    for segment in body.split('/') {
        let first = segment.chars().next().ok_or("expected no empty segment (// or a trailing /)")?;
        if first.is_ascii_digit() {
            return Err(format!("segment `{segment}` starts with a digit"));
        }
        if let Some(bad) = segment.chars().find(|c| !(c.is_ascii_alphanumeric() || *c == '_')) {
            return Err(format!("`{bad}` in segment `{segment}`: expected letters, digits and _"));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::POSE_WITH_COVARIANCE_STAMPED;

    #[test]
    fn keys_and_tokens_follow_rmw_zenoh() {
        let key = topic_key(0, "/poseflow/obj_000005/pose", &POSE_WITH_COVARIANCE_STAMPED, true);
        assert_eq!(
            key,
            "0/poseflow/obj_000005/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/\
             RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
        );
        assert_eq!(
            topic_key(0, "/a", &POSE_WITH_COVARIANCE_STAMPED, false),
            "0/a/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/TypeHashNotSupported"
        );
        let node = RosNode {
            domain: 7,
            session: "ab12".into(),
            node_id: 0,
            namespace: "/".into(),
            name: "poseflow".into(),
            type_hashes: true,
        };
        assert_eq!(node.token(), "@ros2_lv/7/ab12/0/0/NN/%/%/poseflow");
        let token = node.endpoint_token(3, EndpointKind::Publisher, "/a/b", &POSE_WITH_COVARIANCE_STAMPED);
        assert!(token.starts_with("@ros2_lv/7/ab12/0/3/MP/%/%/poseflow/%a%b/geometry_msgs::msg::dds_::"), "{token}");
        assert!(token.ends_with("/::,10:,:,:,,"), "{token}");
    }

    #[test]
    fn attachments_round_trip_and_garbage_is_not_one() {
        let a = Attachment { sequence: 42, source_time_ns: 1_700_000_000_000_000_000, gid: [9; GID_LEN] };
        let bytes = a.encode();
        assert_eq!(bytes.len(), 33);
        assert_eq!(Attachment::decode(&bytes), Some(a));
        assert_eq!(Attachment::decode(&bytes[..20]), None);
    }

    #[test]
    fn topic_names_are_checked_as_ros_does() {
        assert!(check_topic("/poseflow/obj_000001/pose").is_ok());
        for (bad, why) in
            [("poseflow", "absolute"), ("/a//b", "empty"), ("/a/", "empty"), ("/1a", "digit"), ("/a-b", "`-`")]
        {
            let err = check_topic(bad).unwrap_err();
            assert!(err.contains(why), "{bad}: {err}");
        }
    }
}
