//! One Zenoh session acting as one ROS 2 node: its connection parameters,
//! its liveliness tokens, and its publishers and subscriptions in
//! rmw_zenoh's conventions ([`crate::rmw`]).

use serde::Deserialize;
use zenoh::Wait;
use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;

use crate::Ros2Error;
use crate::msgs::RosType;
use crate::rmw::{Attachment, EndpointKind, GID_LEN, RosNode, topic_key};

/// How a stage joins the ROS 2 graph: the parameters every ROS 2 stage
/// takes besides its own.
///
/// | key | default | meaning |
/// |---|---|---|
/// | `mode` | `"peer"` | Zenoh mode, `peer` or `client` |
/// | `connect` | `["tcp/localhost:7447"]` | endpoints to connect to: the rmw_zenoh router (`ros2 run rmw_zenoh_cpp rmw_zenohd`) listens there by default |
/// | `listen` | `[]` | endpoints to listen on (a peer that ROS 2 nodes connect to) |
/// | `domain_id` | `ROS_DOMAIN_ID`, else 0 | the ROS domain |
/// | `namespace` | `"/"` | the node's namespace |
/// | `node_name` | the stage's own | the node's name in `ros2 node list` |
/// | `ros_distro` | `"jazzy"` | the ROS 2 release of the other nodes: `humble` names types without a hash (`TypeHashNotSupported`), `jazzy`, `kilted` and `rolling` with their RIHS01 hash; nodes of the two kinds do not see each other's topics |
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Connection {
    #[serde(default = "peer")]
    pub mode: String,
    #[serde(default = "router")]
    pub connect: Vec<String>,
    #[serde(default)]
    pub listen: Vec<String>,
    pub domain_id: Option<u32>,
    #[serde(default = "root")]
    pub namespace: String,
    pub node_name: Option<String>,
    #[serde(default = "jazzy")]
    pub ros_distro: String,
}

fn jazzy() -> String {
    "jazzy".into()
}

fn peer() -> String {
    "peer".into()
}
fn router() -> Vec<String> {
    vec!["tcp/localhost:7447".into()]
}
fn root() -> String {
    "/".into()
}

/// The keys of [`Connection`].
const CONNECTION_KEYS: [&str; 7] = ["mode", "connect", "listen", "domain_id", "namespace", "node_name", "ros_distro"];

impl Connection {
    /// Takes the connection keys out of a stage's `params`, leaving the
    /// stage's own for it to check.
    pub fn take(params: &mut serde_json::Value) -> Result<Self, Ros2Error> {
        let mut taken = serde_json::Map::new();
        if let Some(table) = params.as_object_mut() {
            for key in CONNECTION_KEYS {
                if let Some(value) = table.remove(key) {
                    taken.insert(key.to_string(), value);
                }
            }
        }
        let connection: Self = serde_json::from_value(taken.into())
            .map_err(|err| Ros2Error::Params { key: "connection".into(), detail: err.to_string() })?;
        if !["peer", "client"].contains(&connection.mode.as_str()) {
            return Err(Ros2Error::Params {
                key: "mode".into(),
                detail: format!("{:?}: expected \"peer\" or \"client\"", connection.mode),
            });
        }
        if connection.mode == "client" && connection.connect.is_empty() {
            return Err(Ros2Error::Params {
                key: "connect".into(),
                detail: "a client needs an endpoint to connect to (the rmw_zenoh router)".into(),
            });
        }
        if !["humble", "jazzy", "kilted", "rolling"].contains(&connection.ros_distro.as_str()) {
            return Err(Ros2Error::Params {
                key: "ros_distro".into(),
                detail: format!(
                    "{:?}: expected \"humble\", \"jazzy\", \"kilted\" or \"rolling\" (the first with rmw_zenoh)",
                    connection.ros_distro
                ),
            });
        }
        if !connection.namespace.starts_with('/') {
            return Err(Ros2Error::Params {
                key: "namespace".into(),
                detail: format!(
                    "{:?}: expected an absolute namespace such as \"/\" or \"/robot\"",
                    connection.namespace
                ),
            });
        }
        Ok(connection)
    }

    fn domain(&self) -> Result<u32, Ros2Error> {
        if let Some(domain) = self.domain_id {
            return Ok(domain);
        }
        match std::env::var("ROS_DOMAIN_ID") {
            Ok(text) if !text.trim().is_empty() => text.trim().parse().map_err(|_| Ros2Error::Params {
                key: "domain_id".into(),
                detail: format!("ROS_DOMAIN_ID={text:?}: expected a number 0–232"),
            }),
            _ => Ok(0),
        }
    }
}

/// A Zenoh session that is one ROS 2 node.
pub struct RosSession {
    session: zenoh::Session,
    node: RosNode,
    next_entity: u32,
    _token: zenoh::liveliness::LivelinessToken,
}

impl std::fmt::Debug for RosSession {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RosSession").field("node", &self.node).finish_non_exhaustive()
    }
}

fn zenoh_error(operation: &'static str, target: &str) -> impl FnOnce(zenoh::Error) -> Ros2Error {
    let target = target.to_string();
    move |err| Ros2Error::Zenoh { operation, target, detail: err.to_string() }
}

impl RosSession {
    /// Opens the session and announces the node `default_name` (or the
    /// connection's `node_name`).
    pub fn open(connection: &Connection, default_name: &str) -> Result<Self, Ros2Error> {
        let domain = connection.domain()?;
        let config = poseflow_bridge::session_config(&connection.mode, &connection.connect, &connection.listen, false)
            .map_err(|(key, err)| zenoh_error("configure", key)(err))?;
        let session = zenoh::open(config).wait().map_err(zenoh_error("open a session for", default_name))?;
        let node = RosNode {
            domain,
            session: session.zid().to_string(),
            node_id: 0,
            namespace: connection.namespace.clone(),
            name: connection.node_name.clone().unwrap_or_else(|| default_name.to_string()),
            type_hashes: connection.ros_distro != "humble",
        };
        let token =
            session.liveliness().declare_token(node.token()).wait().map_err(zenoh_error("declare", &node.token()))?;
        tracing::info!(node = %node.name, domain, zid = %node.session, "ROS 2 node up");
        Ok(Self { session, node, next_entity: 1, _token: token })
    }

    fn entity(&mut self) -> u32 {
        self.next_entity += 1;
        self.next_entity - 1
    }

    fn declare(
        &mut self,
        kind: EndpointKind,
        topic: &str,
        ty: &RosType,
    ) -> Result<(u32, zenoh::liveliness::LivelinessToken), Ros2Error> {
        let entity = self.entity();
        let token = self.node.endpoint_token(entity, kind, topic, ty);
        let token =
            self.session.liveliness().declare_token(token.clone()).wait().map_err(zenoh_error("declare", &token))?;
        Ok((entity, token))
    }

    /// A publisher of `ty` on `topic`, announced to the ROS graph.
    pub fn publisher(&mut self, topic: &str, ty: &RosType) -> Result<RosPublisher, Ros2Error> {
        let key = topic_key(self.node.domain, topic, ty, self.node.type_hashes);
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .encoding(Encoding::APPLICATION_CDR)
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(zenoh_error("declare a publisher on", &key))?;
        let (entity, token) = self.declare(EndpointKind::Publisher, topic, ty)?;
        Ok(RosPublisher { publisher, gid: gid(&self.node.session, entity), sequence: 0, _token: token })
    }

    /// A subscription to `ty` on `topic`, announced to the ROS graph; each
    /// message's CDR bytes go to `deliver`, on a Zenoh thread.
    pub fn subscribe(
        &mut self,
        topic: &str,
        ty: &RosType,
        deliver: impl Fn(Vec<u8>) + Send + Sync + 'static,
    ) -> Result<RosSubscription, Ros2Error> {
        let key = topic_key(self.node.domain, topic, ty, self.node.type_hashes);
        let subscriber = self
            .session
            .declare_subscriber(key.clone())
            .callback(move |sample| deliver(sample.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zenoh_error("subscribe to", &key))?;
        let (_, token) = self.declare(EndpointKind::Subscription, topic, ty)?;
        Ok(RosSubscription { _subscriber: subscriber, _token: token })
    }
}

/// A publisher's GID: the session id's bytes with the entity id mixed into
/// the last four, unique per publisher of a session.
fn gid(session: &str, entity: u32) -> [u8; GID_LEN] {
    let mut gid = [0u8; GID_LEN];
    let digits: Vec<u8> = session.bytes().rev().filter_map(|c| (c as char).to_digit(16).map(|d| d as u8)).collect();
    for (i, pair) in digits.chunks(2).take(GID_LEN).enumerate() {
        gid[GID_LEN - 1 - i] = pair[0] | pair.get(1).map_or(0, |high| high << 4);
    }
    for (byte, mix) in gid[GID_LEN - 4..].iter_mut().zip(entity.to_be_bytes()) {
        *byte ^= mix;
    }
    gid
}

/// A topic publisher of a [`RosSession`].
#[derive(Debug)]
pub struct RosPublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
    gid: [u8; GID_LEN],
    sequence: u64,
    _token: zenoh::liveliness::LivelinessToken,
}

impl RosPublisher {
    /// Publishes one CDR-encoded message.
    pub fn put(&mut self, cdr: Vec<u8>) -> Result<(), Ros2Error> {
        self.sequence += 1;
        let attachment = Attachment {
            sequence: self.sequence,
            source_time_ns: poseflow_contracts::stamp_clock_ns() as i64,
            gid: self.gid,
        };
        let key = self.publisher.key_expr().to_string();
        self.publisher.put(cdr).attachment(attachment.encode()).wait().map_err(zenoh_error("put on", &key))
    }
}

/// A subscription of a [`RosSession`]; dropping it unsubscribes.
#[derive(Debug)]
pub struct RosSubscription {
    _subscriber: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn connection_keys_are_taken_and_checked() {
        let mut params = serde_json::json!({ "listen": ["tcp/127.0.0.1:7000"], "frame_id": "cam", "domain_id": 3 });
        let connection = Connection::take(&mut params).unwrap();
        assert_eq!(connection.listen, ["tcp/127.0.0.1:7000"]);
        assert_eq!(connection.connect, ["tcp/localhost:7447"]);
        assert_eq!(connection.domain().unwrap(), 3);
        assert_eq!(params, serde_json::json!({ "frame_id": "cam" }), "the stage's own keys stay");
        let err = Connection::take(&mut serde_json::json!({ "mode": "router" })).unwrap_err().to_string();
        assert!(err.contains("mode") && err.contains("\"router\"") && err.contains("peer"), "{err}");
        let err = Connection::take(&mut serde_json::json!({ "mode": "client", "connect": [] })).unwrap_err();
        assert!(err.to_string().contains("connect"), "{err}");
        let err = Connection::take(&mut serde_json::json!({ "ros_distro": "iron" })).unwrap_err().to_string();
        assert!(err.contains("ros_distro") && err.contains("\"iron\"") && err.contains("humble"), "{err}");
        let err = Connection::take(&mut serde_json::json!({ "namespace": "robot" })).unwrap_err();
        assert!(err.to_string().contains("absolute"), "{err}");
    }

    #[test]
    fn gids_differ_per_entity_and_keep_the_session() {
        let a = gid("1f2e3d4c5b6a79880011223344556677", 1);
        let b = gid("1f2e3d4c5b6a79880011223344556677", 2);
        assert_ne!(a, b);
        assert_eq!(a[..12], b[..12]);
        assert_eq!(a[0], 0x1f);
    }
}
