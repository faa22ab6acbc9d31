//! Settings of the zenoh session and of the ROS 2 topics it ingests (TOML table `[zenoh]`, array
//! `[[zenoh.ros]]`; every key in `deploy/bgkmap.toml`). Plain data: it builds without zenoh, so a
//! configuration file stays valid for a binary built without the `zenoh` feature (which then
//! refuses `enabled = true` with a clear error).

use serde::Deserialize;

/// The default listen endpoint of a peer: loopback, port 7450 (7447 is the zenoh router's and
/// rmw_zenohd's).
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7450";

/// The zenoh session of `bgkmap serve`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohConfig {
    /// Open a zenoh session. Default false; `--zenoh`, `--zenoh-listen` or `--zenoh-connect`
    /// turn it on.
    pub enabled: bool,
    /// `peer` (default: listens, and connects to `connect`) or `client` (only connects).
    pub mode: ZenohMode,
    /// Endpoints a peer listens on. Default `["tcp/127.0.0.1:7450"]`; port 0 picks a free port
    /// (the bound locators are printed). Ignored by a client.
    pub listen: Vec<String>,
    /// Endpoints to connect to: other peers, or a router (`tcp/127.0.0.1:7447` for rmw_zenohd).
    /// Default none.
    pub connect: Vec<String>,
    /// UDP multicast scouting (discovery on the LAN). Default false: endpoints are explicit.
    pub multicast_scouting: bool,
    /// ROS 2 point cloud topics to ingest (rmw_zenoh keys). Default none.
    pub ros: Vec<RosTopicConfig>,
}

impl Default for ZenohConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            mode: ZenohMode::Peer,
            listen: vec![DEFAULT_LISTEN.to_string()],
            connect: Vec::new(),
            multicast_scouting: false,
            ros: Vec::new(),
        }
    }
}

/// zenoh session modes bgkmap supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ZenohMode {
    Peer,
    Client,
}

impl ZenohMode {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Peer => "peer",
            Self::Client => "client",
        }
    }
}

/// Where a ROS 2 cloud's sensor pose comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RosPose {
    /// The sensor sits at the world origin, unrotated (clouds already in the world frame, seen
    /// from the origin).
    Identity,
    /// A `geometry_msgs/PoseStamped` topic (`pose_topic`) in the world frame, interpolated at
    /// the cloud's stamp.
    Topic,
    /// `/tf` and `/tf_static`: the chain from the world frame down to the cloud's frame.
    Tf,
}

/// One ROS 2 `sensor_msgs/PointCloud2` topic streamed into a map.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RosTopicConfig {
    /// The map (must exist).
    pub map: String,
    /// The ROS topic, e.g. `/robot1/points`.
    pub cloud_topic: String,
    /// The source name of the scans in the map. Default: the topic.
    #[serde(default)]
    pub source: Option<String>,
    /// `ROS_DOMAIN_ID`. Default 0.
    #[serde(default)]
    pub domain_id: u32,
    /// A key expression to subscribe to instead of the rmw_zenoh one (e.g. `robot1/points` from
    /// zenoh-bridge-ros2dds, which publishes the topic name alone).
    #[serde(default)]
    pub cloud_key: Option<String>,
    /// `identity`, `topic` or `tf`. Default `identity`.
    #[serde(default = "default_pose")]
    pub pose: RosPose,
    /// The `geometry_msgs/PoseStamped` topic for `pose = "topic"`.
    #[serde(default)]
    pub pose_topic: Option<String>,
    /// A key expression to subscribe to for poses instead of the rmw_zenoh one.
    #[serde(default)]
    pub pose_key: Option<String>,
    /// The map frame. Default `map`. Clouds in this frame are used as they are; others are moved
    /// into it by their pose.
    #[serde(default = "default_world_frame")]
    pub world_frame: String,
    /// For clouds already in the world frame with `pose = "tf"`: the frame whose origin is the
    /// sensor. Default: none (the world origin).
    #[serde(default)]
    pub sensor_frame: Option<String>,
}

fn default_pose() -> RosPose {
    RosPose::Identity
}

fn default_world_frame() -> String {
    "map".to_string()
}

impl RosTopicConfig {
    /// The source name the map records.
    pub fn source_name(&self) -> &str {
        self.source.as_deref().unwrap_or(&self.cloud_topic)
    }
}

impl ZenohConfig {
    /// Checks what can be checked before opening the session (zenoh checks the endpoints).
    pub fn validate(&self) -> Result<(), String> {
        if self.mode == ZenohMode::Client && self.connect.is_empty() {
            return Err("zenoh mode client needs at least one connect endpoint (--zenoh-connect)".into());
        }
        for (i, r) in self.ros.iter().enumerate() {
            let at = |what: &str| format!("zenoh.ros[{i}].{what}");
            if crate::service::validate_map_name(&r.map).is_err() {
                return Err(format!("{}: {:?} is not a map name", at("map"), r.map));
            }
            if r.cloud_key.is_none() && crate::io::ros2::keys::topic_key(0, &r.cloud_topic, "t").is_none() {
                return Err(format!("{}: {:?} is not a ROS topic name", at("cloud_topic"), r.cloud_topic));
            }
            if r.source_name().is_empty() {
                return Err(format!("{}: must not be empty", at("source")));
            }
            if r.pose == RosPose::Topic && r.pose_topic.is_none() && r.pose_key.is_none() {
                return Err(format!("{}: pose = \"topic\" needs pose_topic (or pose_key)", at("pose_topic")));
            }
            if r.world_frame.is_empty() {
                return Err(format!("{}: must not be empty", at("world_frame")));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_topics_parse_with_defaults_and_are_checked() {
        let c: ZenohConfig = toml::from_str(
            "enabled = true\n[[ros]]\nmap = \"office\"\ncloud_topic = \"/robot1/points\"\n\
             [[ros]]\nmap = \"office\"\ncloud_topic = \"/r2/cloud\"\npose = \"topic\"\npose_topic = \"/r2/pose\"\n",
        )
        .unwrap();
        assert_eq!(c.listen, [DEFAULT_LISTEN]);
        assert_eq!(
            (c.ros[0].pose, c.ros[0].domain_id, c.ros[0].world_frame.as_str()),
            (RosPose::Identity, 0, "map")
        );
        assert_eq!(c.ros[0].source_name(), "/robot1/points");
        c.validate().unwrap();
        let mut bad = c.clone();
        bad.ros[1].pose_topic = None;
        assert!(bad.validate().unwrap_err().contains("zenoh.ros[1].pose_topic"));
        let mut bad = c.clone();
        bad.ros[0].cloud_topic = "/".into();
        assert!(bad.validate().unwrap_err().contains("zenoh.ros[0].cloud_topic"));
        let client = ZenohConfig { mode: ZenohMode::Client, ..ZenohConfig::default() };
        assert!(client.validate().unwrap_err().contains("connect"));
        assert!(
            toml::from_str::<ZenohConfig>("[[ros]]\nmap = \"m\"\ncloud_topic = \"/c\"\nbogus = 1").is_err()
        );
    }
}
