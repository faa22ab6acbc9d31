//! PLY point export (docs/formats.md §4).
//!
//! This module owns the binary little-endian PLY vertex layout bgkmap writes: one vertex per
//! point with `x y z` (float), `red green blue` (uchar) and `probability` (float), no faces.
//! MeshLab and CloudCompare read `probability` as a scalar field.

/// One exported vertex: 19 bytes on disk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlyVertex {
    pub position: [f32; 3],
    pub color: [u8; 3],
    pub probability: f32,
}

/// Bytes per vertex record: 3 × f32 + 3 × u8 + f32.
const VERTEX_BYTES: usize = 19;

/// Writes a `binary_little_endian 1.0` PLY with one vertex element and no faces.
///
/// `comment` goes on a `comment` header line (line breaks are replaced by spaces so the header
/// stays valid); an empty comment writes no comment line.
pub fn write_ply_points(vertices: &[PlyVertex], comment: &str) -> Vec<u8> {
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    if !comment.is_empty() {
        header.push_str("comment ");
        header.push_str(&comment.replace(['\r', '\n'], " "));
        header.push('\n');
    }
    header.push_str(&format!("element vertex {}\n", vertices.len()));
    for p in ["float x", "float y", "float z", "uchar red", "uchar green", "uchar blue", "float probability"]
    {
        header.push_str("property ");
        header.push_str(p);
        header.push('\n');
    }
    header.push_str("end_header\n");
    let mut out = header.into_bytes();
    out.reserve(vertices.len() * VERTEX_BYTES);
    for v in vertices {
        v.position.iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
        out.extend_from_slice(&v.color);
        out.extend_from_slice(&v.probability.to_le_bytes());
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn split_header(bytes: &[u8]) -> (String, &[u8]) {
        let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        (String::from_utf8(bytes[..end].to_vec()).unwrap(), &bytes[end..])
    }

    #[test]
    fn header_matches_spec_and_body_has_19_bytes_per_vertex() {
        let v =
            |i: u8| PlyVertex { position: [f32::from(i), -0.5, 2.25], color: [255, i, 0], probability: 0.75 };
        let verts: Vec<_> = (0..3).map(v).collect();
        let bytes = write_ply_points(&verts, "bgkmap occupied cells, res 0.1");
        let (header, body) = split_header(&bytes);
        assert_eq!(
            header,
            "ply\nformat binary_little_endian 1.0\ncomment bgkmap occupied cells, res 0.1\nelement vertex 3\n\
             property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n\
             property uchar blue\nproperty float probability\nend_header\n"
        );
        assert_eq!(body.len(), 3 * VERTEX_BYTES);
        let second = &body[VERTEX_BYTES..2 * VERTEX_BYTES];
        assert_eq!(f32::from_le_bytes(second[0..4].try_into().unwrap()), 1.0);
        assert_eq!(f32::from_le_bytes(second[8..12].try_into().unwrap()), 2.25);
        assert_eq!(&second[12..15], &[255, 1, 0]);
        assert_eq!(f32::from_le_bytes(second[15..19].try_into().unwrap()), 0.75);
    }

    #[test]
    fn empty_cloud_and_comment_edge_cases() {
        let bytes = write_ply_points(&[], "");
        let (header, body) = split_header(&bytes);
        assert!(!header.contains("comment"));
        assert!(header.contains("element vertex 0\n"));
        assert!(body.is_empty());
        let (header, _) = split_header(&write_ply_points(&[], "two\nlines"));
        assert!(header.contains("comment two lines\nelement vertex 0\n"));
    }
}
