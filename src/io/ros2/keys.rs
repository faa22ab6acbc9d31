//! rmw_zenoh key expressions (docs/formats.md §5.1): `<domain_id>/<topic>/<type name>/<type hash>`,
//! the topic without its leading and trailing `/` (inner ones kept). bgkmap subscribes with `*`
//! in the hash chunk, so every ROS 2 distribution matches (Humble: `TypeHashNotSupported`,
//! Iron and later: `RIHS01_…`).

/// DDS type names of the messages the bridge reads.
pub const POINT_CLOUD2: &str = "sensor_msgs::msg::dds_::PointCloud2_";
pub const POSE_STAMPED: &str = "geometry_msgs::msg::dds_::PoseStamped_";
pub const TF_MESSAGE: &str = "tf2_msgs::msg::dds_::TFMessage_";

/// The key expression matching `topic` of type `type_name` on `domain_id`, any type hash; `None`
/// for a topic that is empty or not a valid key (`*`, `$`, `#`, `?`, empty segments).
pub fn topic_key(domain_id: u32, topic: &str, type_name: &str) -> Option<String> {
    let name = topic.trim_matches('/');
    let valid = !name.is_empty()
        && name.split('/').all(|chunk| !chunk.is_empty())
        && !name.contains(['*', '$', '#', '?', '@']);
    valid.then(|| format!("{domain_id}/{name}/{type_name}/*"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_map_to_rmw_zenoh_keys() {
        assert_eq!(
            topic_key(0, "/robot1/points", POINT_CLOUD2).as_deref(),
            Some("0/robot1/points/sensor_msgs::msg::dds_::PointCloud2_/*")
        );
        assert_eq!(
            topic_key(7, "tf/", TF_MESSAGE).as_deref(),
            Some("7/tf/tf2_msgs::msg::dds_::TFMessage_/*")
        );
        assert_eq!(topic_key(0, "/", POINT_CLOUD2), None);
        assert_eq!(topic_key(0, "/a//b", POINT_CLOUD2), None);
        assert_eq!(topic_key(0, "/a/*", POINT_CLOUD2), None);
    }
}
