//! Decoders for the ROS 2 messages the bridge reads: `sensor_msgs/PointCloud2`,
//! `geometry_msgs/PoseStamped` and `tf2_msgs/TFMessage` (layouts in docs/formats.md §5.3–5.4).
//!
//! A point cloud is read in place: the decoder borrows the payload and copies out only x, y, z.
//! Non-finite points are kept, so the service drops and counts them as it does for every
//! transport. Field names in errors follow the message (`PointCloud2.fields`).

use super::Ros2Error;
use super::cdr::CdrReader;
use crate::core::Pose;

/// `std_msgs/Header`: stamp (ns since the epoch, from `sec` and `nanosec`) and frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header<'a> {
    pub stamp_ns: i64,
    pub frame_id: &'a str,
}

/// `sensor_msgs/PointField` datatype codes used for coordinates.
const FLOAT32: u8 = 7;
const FLOAT64: u8 = 8;

/// One `sensor_msgs/PointField`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PointField<'a> {
    pub name: &'a str,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

/// A decoded `sensor_msgs/PointCloud2`; `data` borrows the payload.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PointCloud2<'a> {
    pub header: Header<'a>,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField<'a>>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    pub data: &'a [u8],
    pub is_dense: bool,
}

/// A decoded `geometry_msgs/PoseStamped`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseStamped<'a> {
    pub header: Header<'a>,
    /// The pose of the body in `header.frame_id` (`frame_from_body`).
    pub pose: Pose,
}

/// One `geometry_msgs/TransformStamped`: `parent_from_child` at `header.stamp_ns`, where the
/// parent is `header.frame_id`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransformStamped<'a> {
    pub header: Header<'a>,
    pub child_frame_id: &'a str,
    pub parent_from_child: Pose,
}

fn header<'a>(r: &mut CdrReader<'a>, msg: &str) -> Result<Header<'a>, Ros2Error> {
    let sec = r.i32(&format!("{msg}.header.stamp.sec"))?;
    let nanosec = r.u32(&format!("{msg}.header.stamp.nanosec"))?;
    if nanosec >= 1_000_000_000 {
        return Err(Ros2Error::Invalid {
            field: format!("{msg}.header.stamp.nanosec"),
            reason: format!("{nanosec} is not below 10^9"),
        });
    }
    let frame_id = r.string(&format!("{msg}.header.frame_id"))?;
    Ok(Header { stamp_ns: i64::from(sec) * 1_000_000_000 + i64::from(nanosec), frame_id })
}

/// Position (x, y, z) then orientation (x, y, z, w), as `geometry_msgs/Pose` and `Transform`
/// both lay them out; returned with the rotation as (w, x, y, z).
fn pose(r: &mut CdrReader<'_>, field: &str) -> Result<Pose, Ros2Error> {
    let mut v = [0.0; 7];
    for x in &mut v {
        *x = r.f64(field)?;
    }
    Ok(Pose { translation_m: [v[0], v[1], v[2]], rotation_wxyz: [v[6], v[3], v[4], v[5]] })
}

impl<'a> PointCloud2<'a> {
    /// Decodes the message (CDR with its encapsulation header).
    pub fn decode(payload: &'a [u8]) -> Result<Self, Ros2Error> {
        let mut r = CdrReader::new(payload)?;
        let header = header(&mut r, "PointCloud2")?;
        let height = r.u32("PointCloud2.height")?;
        let width = r.u32("PointCloud2.width")?;
        let n = r.sequence_len("PointCloud2.fields", 13)?;
        let mut fields = Vec::with_capacity(n);
        for _ in 0..n {
            fields.push(PointField {
                name: r.string("PointCloud2.fields.name")?,
                offset: r.u32("PointCloud2.fields.offset")?,
                datatype: r.u8("PointCloud2.fields.datatype")?,
                count: r.u32("PointCloud2.fields.count")?,
            });
        }
        let is_bigendian = r.bool("PointCloud2.is_bigendian")?;
        let point_step = r.u32("PointCloud2.point_step")?;
        let row_step = r.u32("PointCloud2.row_step")?;
        let len = r.sequence_len("PointCloud2.data", 1)?;
        let data = r.bytes(len, "PointCloud2.data")?;
        let is_dense = r.bool("PointCloud2.is_dense")?;
        Ok(Self { header, height, width, fields, is_bigendian, point_step, row_step, data, is_dense })
    }

    /// Byte offset and width (4 or 8) of coordinate `name` inside a point record.
    fn coordinate(&self, name: &str) -> Result<(usize, usize), Ros2Error> {
        let field = || format!("PointCloud2.fields[{name}]");
        let f = self.fields.iter().find(|f| f.name == name).ok_or_else(|| Ros2Error::Invalid {
            field: "PointCloud2.fields".into(),
            reason: format!("no field named {name:?}"),
        })?;
        let size = match f.datatype {
            FLOAT32 => 4,
            FLOAT64 => 8,
            d => {
                let reason = format!("datatype {d}; coordinates must be FLOAT32 (7) or FLOAT64 (8)");
                return Err(Ros2Error::Invalid { field: field(), reason });
            }
        };
        if f.count == 0 {
            return Err(Ros2Error::Invalid { field: field(), reason: "count is 0".into() });
        }
        if f.offset as usize + size > self.point_step as usize {
            let reason = format!("offset {} + {size} bytes exceeds point_step {}", f.offset, self.point_step);
            return Err(Ros2Error::Invalid { field: field(), reason });
        }
        Ok((f.offset as usize, size))
    }

    /// Every point's (x, y, z), row by row; non-finite points are kept (see the module docs).
    pub fn points_xyz(&self) -> Result<Vec<[f32; 3]>, Ros2Error> {
        if self.is_bigendian {
            let reason = "big-endian point data is not supported".into();
            return Err(Ros2Error::Invalid { field: "PointCloud2.is_bigendian".into(), reason });
        }
        let axes = [self.coordinate("x")?, self.coordinate("y")?, self.coordinate("z")?];
        let (rows, cols) = (self.height as usize, self.width as usize);
        let (step, row_step) = (self.point_step as usize, self.row_step as usize);
        let row_bytes = cols.checked_mul(step).filter(|b| rows <= 1 || *b <= row_step);
        let Some(row_bytes) = row_bytes else {
            let reason = format!("width {cols} × point_step {step} exceeds row_step {row_step}");
            return Err(Ros2Error::Invalid { field: "PointCloud2.row_step".into(), reason });
        };
        let needed = match rows {
            0 => Some(0),
            _ => (rows - 1).checked_mul(row_step).and_then(|b| b.checked_add(row_bytes)),
        };
        if needed.is_none_or(|n| n > self.data.len()) {
            let reason = format!(
                "{} bytes hold fewer than height {rows} × width {cols} points of {step} bytes (row_step {row_step})",
                self.data.len()
            );
            return Err(Ros2Error::Invalid { field: "PointCloud2.data".into(), reason });
        }
        let mut out = Vec::with_capacity(rows * cols);
        for row in 0..rows {
            let row_data = &self.data[row * row_step..row * row_step + row_bytes];
            out.extend(row_data.chunks_exact(step.max(1)).take(cols).map(|p| axes.map(|a| coordinate(p, a))));
        }
        Ok(out)
    }
}

/// One little-endian coordinate of a point record (f64 narrowed to f32).
fn coordinate(point: &[u8], (offset, size): (usize, usize)) -> f32 {
    let b = &point[offset..offset + size];
    match b {
        [a, b, c, d] => f32::from_le_bytes([*a, *b, *c, *d]),
        _ => {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            f64::from_le_bytes(a) as f32
        }
    }
}

impl<'a> PoseStamped<'a> {
    pub fn decode(payload: &'a [u8]) -> Result<Self, Ros2Error> {
        let mut r = CdrReader::new(payload)?;
        let header = header(&mut r, "PoseStamped")?;
        let pose = pose(&mut r, "PoseStamped.pose")?;
        Ok(Self { header, pose })
    }
}

/// Decodes a `tf2_msgs/TFMessage` (a sequence of `TransformStamped`).
pub fn decode_tf_message(payload: &[u8]) -> Result<Vec<TransformStamped<'_>>, Ros2Error> {
    let mut r = CdrReader::new(payload)?;
    // Smallest element: stamp 8 + two empty strings 5 + 5 + 7 f64 (56), before padding.
    let n = r.sequence_len("TFMessage.transforms", 74)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let header = header(&mut r, "TFMessage.transforms")?;
        let child_frame_id = r.string("TFMessage.transforms.child_frame_id")?;
        let parent_from_child = pose(&mut r, "TFMessage.transforms.transform")?;
        out.push(TransformStamped { header, child_frame_id, parent_from_child });
    }
    Ok(out)
}

#[cfg(test)]
#[path = "msgs_tests.rs"]
mod tests;
