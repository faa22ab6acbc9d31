//! ROS 2 messages without ROS: the CDR codec of the point clouds and poses a ROS 2 robot
//! publishes (over rmw_zenoh or zenoh-bridge-ros2dds), and the sensor pose at a cloud's stamp.
//!
//! - [`cdr`]: the CDR reader (encapsulation header, alignment from the body start);
//! - [`msgs`]: `sensor_msgs/PointCloud2`, `geometry_msgs/PoseStamped`, `tf2_msgs/TFMessage`;
//! - [`tf`]: pose histories and the transform tree, interpolated at a stamp;
//! - [`keys`]: rmw_zenoh key expressions for a topic.
//!
//! Pure: byte slices in, values out; no network, no async.

pub mod cdr;
pub mod keys;
pub mod msgs;
pub mod tf;

pub use msgs::{Header, PointCloud2, PointField, PoseStamped, TransformStamped, decode_tf_message};

/// Why a ROS 2 message could not be decoded; names the field.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Ros2Error {
    #[error(
        "not plain CDR: encapsulation id {0:02x?} (expected [00, 01] little-endian or [00, 00] big-endian)"
    )]
    Encapsulation([u8; 2]),
    #[error("{field}: the message ends too early (body offset {at})")]
    Truncated { field: String, at: usize },
    #[error("{field}: {reason}")]
    Invalid { field: String, reason: String },
}
