//! PCD (Point Cloud Library v0.7) reader and writer.
//!
//! This module owns the PCD header grammar (docs/formats.md §3.1) and the three payload modes:
//! `ascii`, `binary` (array of structs) and `binary_compressed` (LZF, struct of arrays, via
//! [`crate::io::lzf`]). The reader extracts only x/y/z (F4 or F8), skips every other field by
//! its byte size, reads exactly `POINTS` records, ignores trailing bytes and drops non-finite
//! points. It returns errors for malformed input and never panics. The writers emit plain
//! `x y z` F4 clouds.

use crate::io::lzf::{self, LzfError};

/// Header lines scanned before giving up on finding `DATA`.
const MAX_HEADER_LINES: usize = 1024;
/// Header bytes scanned before giving up on finding `DATA`.
const MAX_HEADER_BYTES: usize = 1 << 20;

/// A decoded point cloud.
#[derive(Debug, Clone, PartialEq)]
pub struct PcdCloud {
    /// Finite points, in file order.
    pub points: Vec<[f32; 3]>,
    /// `VIEWPOINT tx ty tz qw qx qy qz`, parsed as f32 and widened; `None` if the line is absent.
    pub viewpoint: Option<[f64; 7]>,
    /// Points skipped because a coordinate was NaN or infinite.
    pub dropped_nonfinite: usize,
    pub width: u32,
    pub height: u32,
}

/// Why a PCD file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum PcdError {
    #[error("PCD header: missing {0} line")]
    MissingLine(&'static str),
    #[error("PCD header: line {line}: {msg}")]
    BadLine { line: usize, msg: String },
    #[error("PCD header: {0}")]
    Header(String),
    #[error("PCD header: POINTS {points} does not equal WIDTH {width} × HEIGHT {height}")]
    PointsMismatch { points: u64, width: u32, height: u32 },
    #[error("PCD: no x/y/z fields (field '{0}' not found)")]
    NoXyz(&'static str),
    #[error("PCD: field '{name}' is {ty}{size} with COUNT {count}; x/y/z must be F4 or F8 with COUNT 1")]
    BadXyzType { name: &'static str, ty: char, size: usize, count: usize },
    #[error("PCD data: expected {expected} bytes of binary data, found {found} (file truncated?)")]
    Truncated { expected: usize, found: usize },
    #[error("PCD data: expected {expected} ascii points, found {found} (file truncated?)")]
    AsciiTruncated { expected: usize, found: usize },
    #[error("PCD data: ascii line {line}: {msg}")]
    Ascii { line: usize, msg: String },
    #[error(
        "PCD data: binary_compressed block says {found} uncompressed bytes, expected {expected} (POINTS × record size)"
    )]
    CompressedSize { expected: usize, found: usize },
    #[error("PCD data: binary_compressed stream: {0}")]
    Lzf(#[from] LzfError),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Ascii,
    Binary,
    Compressed,
}

#[derive(Debug)]
struct Field {
    name: String,
    size: usize,
    ty: char,
    count: usize,
}

/// Where one coordinate lives: byte offset within a record (AoS) or field block start ÷ POINTS
/// (SoA), and token index within an ascii line.
#[derive(Debug, Clone, Copy)]
struct Coord {
    offset: usize,
    token: usize,
    wide: bool,
}

#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    width: u32,
    height: u32,
    points: usize,
    viewpoint: Option<[f64; 7]>,
    mode: Mode,
    data_start: usize,
}

#[derive(Debug, Default)]
struct RawHeader {
    fields: Option<Vec<String>>,
    sizes: Option<Vec<usize>>,
    types: Option<Vec<String>>,
    counts: Option<Vec<usize>>,
    width: Option<u32>,
    height: Option<u32>,
    points: Option<u64>,
    viewpoint: Option<[f64; 7]>,
}

/// Decodes a PCD file held in memory.
pub fn read_pcd(bytes: &[u8]) -> Result<PcdCloud, PcdError> {
    let header = parse_header(bytes)?;
    let coords = locate_xyz(&header.fields)?;
    let record = record_size(&header.fields)?;
    let data = bytes.get(header.data_start..).unwrap_or_default();
    let (points, dropped) = match header.mode {
        Mode::Ascii => read_ascii(data, &header, coords)?,
        Mode::Binary => {
            let expected = data_len(header.points, record)?;
            if data.len() < expected {
                return Err(PcdError::Truncated { expected, found: data.len() });
            }
            extract(data, header.points, coords.map(|c| (c.offset, record, c.wide)))
        }
        Mode::Compressed => {
            let expected = data_len(header.points, record)?;
            let soa = decompress_block(data, expected)?;
            let n = header.points;
            extract(&soa, n, coords.map(|c| (c.offset * n, if c.wide { 8 } else { 4 }, c.wide)))
        }
    };
    Ok(PcdCloud {
        points,
        viewpoint: header.viewpoint,
        dropped_nonfinite: dropped,
        width: header.width,
        height: header.height,
    })
}

fn parse_header(bytes: &[u8]) -> Result<Header, PcdError> {
    let mut raw = RawHeader::default();
    let mut pos = 0;
    let mut line_no = 0;
    loop {
        if line_no >= MAX_HEADER_LINES || pos >= MAX_HEADER_BYTES {
            return Err(PcdError::Header(format!(
                "no DATA line within the first {MAX_HEADER_LINES} lines / {MAX_HEADER_BYTES} bytes"
            )));
        }
        if pos >= bytes.len() {
            return Err(PcdError::MissingLine("DATA"));
        }
        let rest = &bytes[pos..];
        let len = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
        pos = (pos + len + 1).min(bytes.len());
        line_no += 1;
        let bad = |msg: String| PcdError::BadLine { line: line_no, msg };
        let text = std::str::from_utf8(&rest[..len]).map_err(|_| bad("not valid UTF-8 text".into()))?;
        let mut toks = text.split_ascii_whitespace();
        let Some(keyword) = toks.next() else { continue };
        if keyword.starts_with('#') {
            continue;
        }
        let vals: Vec<&str> = toks.collect();
        if keyword == "DATA" {
            let mode = match vals.as_slice() {
                ["ascii"] => Mode::Ascii,
                ["binary"] => Mode::Binary,
                ["binary_compressed"] => Mode::Compressed,
                _ => return Err(bad(format!("unsupported DATA mode '{}'", vals.join(" ")))),
            };
            return finish_header(raw, mode, pos);
        }
        apply_keyword(&mut raw, keyword, &vals).map_err(bad)?;
    }
}

fn apply_keyword(raw: &mut RawHeader, keyword: &str, vals: &[&str]) -> Result<(), String> {
    match keyword {
        "VERSION" => {}
        "FIELDS" | "COLUMNS" => raw.fields = Some(vals.iter().map(|s| s.to_string()).collect()),
        "SIZE" => raw.sizes = Some(parse_list(keyword, vals)?),
        "TYPE" => raw.types = Some(vals.iter().map(|s| s.to_string()).collect()),
        "COUNT" => raw.counts = Some(parse_list(keyword, vals)?),
        "WIDTH" => raw.width = Some(parse_one(keyword, vals)?),
        "HEIGHT" => raw.height = Some(parse_one(keyword, vals)?),
        "POINTS" => raw.points = Some(parse_one(keyword, vals)?),
        "VIEWPOINT" => {
            let v: Vec<f32> = parse_list(keyword, vals)?;
            match v.as_slice() {
                &[a, b, c, d, e, f, g] if v.iter().all(|x| x.is_finite()) => {
                    raw.viewpoint = Some([a, b, c, d, e, f, g].map(f64::from));
                }
                _ => return Err(format!("VIEWPOINT needs 7 finite numbers, got '{}'", vals.join(" "))),
            }
        }
        other => return Err(format!("unknown keyword '{other}'")),
    }
    Ok(())
}

fn parse_list<T: std::str::FromStr>(keyword: &str, vals: &[&str]) -> Result<Vec<T>, String> {
    vals.iter().map(|v| v.parse().map_err(|_| format!("{keyword}: invalid value '{v}'"))).collect()
}

fn parse_one<T: std::str::FromStr>(keyword: &str, vals: &[&str]) -> Result<T, String> {
    match vals {
        [v] => v.parse().map_err(|_| format!("{keyword}: invalid value '{v}'")),
        _ => Err(format!("{keyword} takes one value, got {}", vals.len())),
    }
}

fn finish_header(raw: RawHeader, mode: Mode, data_start: usize) -> Result<Header, PcdError> {
    let names = raw.fields.ok_or(PcdError::MissingLine("FIELDS"))?;
    let sizes = raw.sizes.ok_or(PcdError::MissingLine("SIZE"))?;
    let types = raw.types.ok_or(PcdError::MissingLine("TYPE"))?;
    let counts = raw.counts.unwrap_or_else(|| vec![1; names.len()]);
    let width = raw.width.ok_or(PcdError::MissingLine("WIDTH"))?;
    let height = raw.height.ok_or(PcdError::MissingLine("HEIGHT"))?;
    let points = raw.points.ok_or(PcdError::MissingLine("POINTS"))?;
    if names.is_empty() {
        return Err(PcdError::Header("FIELDS lists no fields".into()));
    }
    if sizes.len() != names.len() || types.len() != names.len() || counts.len() != names.len() {
        return Err(PcdError::Header(format!(
            "FIELDS has {} entries but SIZE has {}, TYPE {}, COUNT {}",
            names.len(),
            sizes.len(),
            types.len(),
            counts.len()
        )));
    }
    if points != u64::from(width) * u64::from(height) {
        return Err(PcdError::PointsMismatch { points, width, height });
    }
    let points =
        usize::try_from(points).map_err(|_| PcdError::Header(format!("POINTS {points} too large")))?;
    let mut fields = Vec::with_capacity(names.len());
    for (((name, size), ty), count) in names.into_iter().zip(sizes).zip(types).zip(counts) {
        let ty = match ty.as_str() {
            "F" => 'F',
            "I" => 'I',
            "U" => 'U',
            _ => return Err(PcdError::Header(format!("field '{name}': unknown TYPE '{ty}'"))),
        };
        if ![1, 2, 4, 8].contains(&size) || count == 0 {
            return Err(PcdError::Header(format!("field '{name}': invalid SIZE {size} / COUNT {count}")));
        }
        fields.push(Field { name, size, ty, count });
    }
    Ok(Header { fields, width, height, points, viewpoint: raw.viewpoint, mode, data_start })
}

/// Byte offset (within one record) and token index of x, y and z.
fn locate_xyz(fields: &[Field]) -> Result<[Coord; 3], PcdError> {
    let mut found: [Option<Coord>; 3] = [None; 3];
    let (mut offset, mut token) = (0usize, 0usize);
    for f in fields {
        if let Some(axis) = ["x", "y", "z"].iter().position(|n| *n == f.name) {
            let name = ["x", "y", "z"][axis];
            if f.ty != 'F' || !(f.size == 4 || f.size == 8) || f.count != 1 {
                return Err(PcdError::BadXyzType { name, ty: f.ty, size: f.size, count: f.count });
            }
            if found[axis].is_some() {
                return Err(PcdError::Header(format!("duplicate field '{name}'")));
            }
            found[axis] = Some(Coord { offset, token, wide: f.size == 8 });
        }
        offset = offset.saturating_add(f.size.saturating_mul(f.count));
        token = token.saturating_add(f.count);
    }
    let get = |axis: usize, name| found[axis].ok_or(PcdError::NoXyz(name));
    Ok([get(0, "x")?, get(1, "y")?, get(2, "z")?])
}

fn record_size(fields: &[Field]) -> Result<usize, PcdError> {
    fields
        .iter()
        .try_fold(0usize, |acc, f| f.size.checked_mul(f.count).and_then(|b| acc.checked_add(b)))
        .ok_or_else(|| PcdError::Header("record size overflows".into()))
}

fn data_len(points: usize, record: usize) -> Result<usize, PcdError> {
    points
        .checked_mul(record)
        .ok_or_else(|| PcdError::Header(format!("{points} points × {record} bytes overflows")))
}

/// Reads `u32 compressed, u32 uncompressed` and inflates the LZF block to `expected` bytes.
fn decompress_block(data: &[u8], expected: usize) -> Result<Vec<u8>, PcdError> {
    let word = |i: usize| -> Result<usize, PcdError> {
        let b = data.get(i..i + 4).ok_or(PcdError::Truncated { expected: 8, found: data.len() })?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let (packed, unpacked) = (word(0)?, word(4)?);
    if unpacked != expected {
        return Err(PcdError::CompressedSize { expected, found: unpacked });
    }
    let body =
        data.get(8..8 + packed).ok_or(PcdError::Truncated { expected: 8 + packed, found: data.len() })?;
    Ok(lzf::decompress(body, expected)?)
}

/// Pulls `n` points out of `data`; `axes` gives (base, stride, is_f64) per coordinate.
fn extract(data: &[u8], n: usize, axes: [(usize, usize, bool); 3]) -> (Vec<[f32; 3]>, usize) {
    let mut points = Vec::with_capacity(n);
    let mut dropped = 0;
    for i in 0..n {
        let p = axes.map(|(base, stride, wide)| {
            let o = base + i * stride;
            if wide {
                let b = &data[o..o + 8];
                f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
            } else {
                f32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]])
            }
        });
        push_point(&mut points, &mut dropped, p);
    }
    (points, dropped)
}

fn push_point(points: &mut Vec<[f32; 3]>, dropped: &mut usize, p: [f32; 3]) {
    if p.iter().all(|v| v.is_finite()) {
        points.push(p);
    } else {
        *dropped += 1;
    }
}

fn read_ascii(data: &[u8], header: &Header, coords: [Coord; 3]) -> Result<(Vec<[f32; 3]>, usize), PcdError> {
    let per_line: usize = header.fields.iter().map(|f| f.count).sum();
    let mut points = Vec::with_capacity(header.points.min(data.len() / 6));
    let (mut seen, mut dropped) = (0, 0);
    for (i, raw) in data.split(|&b| b == b'\n').enumerate() {
        if seen == header.points {
            break;
        }
        let err = |msg: String| PcdError::Ascii { line: i + 1, msg };
        let text = std::str::from_utf8(raw).map_err(|_| err("not valid UTF-8 text".into()))?;
        let toks: Vec<&str> = text.split_ascii_whitespace().collect();
        if toks.is_empty() {
            continue;
        }
        if toks.len() != per_line {
            return Err(err(format!("expected {per_line} values, found {}", toks.len())));
        }
        let mut p = [0f32; 3];
        for (v, c) in p.iter_mut().zip(coords) {
            let t = toks[c.token];
            let parsed = if c.wide { t.parse::<f64>().map(|v| v as f32).ok() } else { t.parse::<f32>().ok() };
            *v = parsed.ok_or_else(|| err(format!("invalid number '{t}'")))?;
        }
        push_point(&mut points, &mut dropped, p);
        seen += 1;
    }
    if seen < header.points {
        return Err(PcdError::AsciiTruncated { expected: header.points, found: seen });
    }
    Ok((points, dropped))
}

fn xyz_header(n: usize, viewpoint: [f64; 7], mode: &str) -> String {
    let vp: Vec<String> = viewpoint.iter().map(|v| format!("{}", *v as f32)).collect();
    format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n\
         COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT {}\nPOINTS {n}\nDATA {mode}\n",
        vp.join(" ")
    )
}

/// Writes an unorganised `x y z` F4 cloud with `DATA binary`.
pub fn write_pcd_binary(points: &[[f32; 3]], viewpoint: [f64; 7]) -> Vec<u8> {
    let mut out = xyz_header(points.len(), viewpoint, "binary").into_bytes();
    out.reserve(points.len() * 12);
    for v in points.iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Writes an unorganised `x y z` cloud with `DATA ascii` (NaN as `nan`); mainly for tests.
pub fn write_pcd_ascii(points: &[[f32; 3]], viewpoint: [f64; 7]) -> Vec<u8> {
    let mut out = xyz_header(points.len(), viewpoint, "ascii");
    for p in points {
        let vals: Vec<String> =
            p.iter().map(|v| if v.is_nan() { "nan".into() } else { v.to_string() }).collect();
        out.push_str(&vals.join(" "));
        out.push('\n');
    }
    out.into_bytes()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const VP: [f64; 7] = [1.5, -2.0, 0.25, 1.0, 0.0, 0.0, 0.0];

    /// A file of the sample data; the tests calling this are ignored unless build.rs found it.
    fn sample(name: &str) -> Vec<u8> {
        let path = format!("{}/../shared/data/la3dm/sim_structured/{name}", env!("CARGO_MANIFEST_DIR"));
        std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
    }

    fn header(fields: &str, sizes: &str, types: &str, counts: &str, n: usize, mode: &str) -> Vec<u8> {
        format!(
            "# comment\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n\
             WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA {mode}\n"
        )
        .into_bytes()
    }

    #[test]
    #[cfg_attr(not(bgkmap_sample_data), ignore = "needs the sample data ../shared/data/la3dm")]
    fn reads_sample_scan() {
        let bytes = sample("sim_structured_1.pcd");
        let cloud = read_pcd(&bytes).unwrap();
        assert_eq!(
            (cloud.points.len(), cloud.width, cloud.height, cloud.dropped_nonfinite),
            (3500, 3500, 1, 0)
        );
        let expect = [0.999982f32, 1.00002, 0.0997627, 1.0, 0.0, 0.0, 0.0].map(f64::from);
        assert_eq!(cloud.viewpoint, Some(expect));
        let start = bytes.windows(12).position(|w| w == b"DATA binary\n").unwrap() + 12;
        let x0 = f32::from_le_bytes(bytes[start..start + 4].try_into().unwrap());
        assert_eq!(cloud.points[0][0], x0);
        let r = cloud.points.iter().map(|p| (p[0] - 1.0).hypot(p[1] - 1.0)).fold(0f32, f32::max);
        assert!(r > 5.0 && r < 10.5, "max planar range from (1, 1): {r}");
    }

    #[test]
    #[cfg_attr(not(bgkmap_sample_data), ignore = "needs the sample data ../shared/data/la3dm")]
    fn truncated_sample_is_a_clear_error() {
        let bytes = sample("sim_structured_1.pcd");
        let start = bytes.windows(12).position(|w| w == b"DATA binary\n").unwrap() + 12;
        let err = read_pcd(&bytes[..start + 1200]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "PCD data: expected 56000 bytes of binary data, found 1200 (file truncated?)"
        );
    }

    #[test]
    fn binary_and_ascii_round_trip() {
        let pts = vec![[0.1f32, -2.5, 3.0], [1e-3, 7.25, -0.0], [123.456, 0.0, 1.0]];
        for bytes in [write_pcd_binary(&pts, VP), write_pcd_ascii(&pts, VP)] {
            let cloud = read_pcd(&bytes).unwrap();
            assert_eq!(cloud.points, pts);
            assert_eq!(cloud.viewpoint, Some(VP));
            assert_eq!((cloud.width, cloud.height, cloud.dropped_nonfinite), (3, 1, 0));
        }
        assert!(read_pcd(&write_pcd_binary(&[], VP)).unwrap().points.is_empty());
    }

    #[test]
    fn non_finite_points_are_dropped_and_counted() {
        let pts = [[1.0f32, 2.0, 3.0], [f32::NAN, 0.0, 0.0], [0.0, f32::INFINITY, 0.0], [4.0, 5.0, 6.0]];
        for bytes in [write_pcd_binary(&pts, VP), write_pcd_ascii(&pts, VP)] {
            let cloud = read_pcd(&bytes).unwrap();
            assert_eq!(cloud.points, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
            assert_eq!(cloud.dropped_nonfinite, 2);
        }
    }

    #[test]
    fn skips_other_fields_and_reads_f64() {
        // rgb F4, z F8, a padding field of 3 bytes, y, x: 4 + 8 + 3 + 4 + 4 = 23-byte records.
        let mut bytes = b"FIELDS rgb z _ y x\nSIZE 4 8 1 4 4\nTYPE F F U F F\nCOUNT 1 1 3 1 1\nWIDTH 2\n\
            HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n"
            .to_vec();
        for (x, y, z) in [(1.0f32, 2.0f32, 3.0f64), (-4.0, -5.0, -6.5)] {
            bytes.extend_from_slice(&[9; 4]);
            bytes.extend_from_slice(&z.to_le_bytes());
            bytes.extend_from_slice(&[7; 3]);
            bytes.extend_from_slice(&y.to_le_bytes());
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        bytes.extend_from_slice(&[0; 100]); // trailing bytes are ignored
        let cloud = read_pcd(&bytes).unwrap();
        assert_eq!(cloud.points, vec![[1.0, 2.0, 3.0], [-4.0, -5.0, -6.5]]);
        assert_eq!(cloud.viewpoint, Some([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]));
    }

    /// SoA payload for fields `x y z _` (F4 F4 F4 U1×2) with the given points.
    fn soa(pts: &[[f32; 3]]) -> Vec<u8> {
        let mut soa = Vec::new();
        for axis in 0..3 {
            pts.iter().for_each(|p| soa.extend_from_slice(&p[axis].to_le_bytes()));
        }
        pts.iter().for_each(|_| soa.extend_from_slice(&[0xAB, 0xCD]));
        soa
    }

    fn compressed_file(pts: &[[f32; 3]], stream: &[u8], unpacked: usize) -> Vec<u8> {
        let mut bytes = header("x y z _", "4 4 4 1", "F F F U", "1 1 1 2", pts.len(), "binary_compressed");
        bytes.extend_from_slice(&(stream.len() as u32).to_le_bytes());
        bytes.extend_from_slice(&(unpacked as u32).to_le_bytes());
        bytes.extend_from_slice(stream);
        bytes
    }

    #[test]
    fn binary_compressed_literal_chunks_and_back_references() {
        let pts = [[1.0f32, 2.0, 3.0], [1.0, 2.0, 3.0], [-1.0, 0.5, 8.0]];
        let raw = soa(&pts);
        // Literal-only stream: chunks of at most 32 bytes.
        let literal: Vec<u8> =
            raw.chunks(32).flat_map(|c| [&[(c.len() - 1) as u8][..], c].concat()).collect();
        let cloud = read_pcd(&compressed_file(&pts, &literal, raw.len())).unwrap();
        assert_eq!(cloud.points, pts.to_vec());
        // Hand-made back-reference: x block = 1.0, 1.0, -1.0; copy the first 4 bytes (distance 4).
        let mut stream = vec![3];
        stream.extend_from_slice(&raw[..4]);
        stream.extend_from_slice(&[(2 << 5), 3]); // len 2+2 = 4, distance 3+1 = 4
        stream.extend(raw[8..].chunks(32).flat_map(|c| [&[(c.len() - 1) as u8][..], c].concat()));
        assert_eq!(read_pcd(&compressed_file(&pts, &stream, raw.len())).unwrap().points, pts.to_vec());
        // Our compressor on a larger, repetitive cloud.
        let many: Vec<[f32; 3]> = (0..500).map(|i| [(i % 10) as f32, 1.0, f32::NAN]).collect();
        let raw = soa(&many);
        let packed = lzf::compress(&raw);
        assert!(packed.len() < raw.len() / 4);
        let cloud = read_pcd(&compressed_file(&many, &packed, raw.len())).unwrap();
        assert_eq!((cloud.points.len(), cloud.dropped_nonfinite), (0, 500));
    }

    /// Written by PCL 1.13 `pcl_convert_pcd_ascii_binary … 2` from a 3×2 organised ascii cloud
    /// (x y z intensity) whose fifth point is NaN; PCL pads the file with zeros to 4096 bytes.
    #[test]
    fn reads_pcl_binary_compressed() {
        let mut bytes = b"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\n\
            SIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 3\nHEIGHT 2\nVIEWPOINT 0.5 1 0 1 0 0 0\nPOINTS 6\n\
            DATA binary_compressed\n"
            .to_vec();
        let s = "3d00000060000000040000803f00e0000305c0bf0000c07f200f0340000000e0020301803e801700a020130040e\
                 00203010041801700c0201300002047e00003a00001803f";
        bytes.extend((0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()));
        bytes.extend_from_slice(&[0; 200]);
        let cloud = read_pcd(&bytes).unwrap();
        let a = [1.0, 2.0, 3.0];
        assert_eq!(cloud.points, vec![a, a, a, [-1.5, 0.25, 8.0], [4.0, 5.0, 6.0]]);
        assert_eq!((cloud.width, cloud.height, cloud.dropped_nonfinite), (3, 2, 1));
        assert_eq!(cloud.viewpoint, Some([0.5, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]));
    }

    #[test]
    fn binary_compressed_errors() {
        let pts = [[1.0f32, 2.0, 3.0]];
        let raw = soa(&pts);
        let packed = lzf::compress(&raw);
        let err = read_pcd(&compressed_file(&pts, &packed, raw.len() + 1)).unwrap_err();
        assert!(matches!(err, PcdError::CompressedSize { expected: 14, found: 15 }), "{err}");
        let file = compressed_file(&pts, &packed, raw.len());
        assert!(matches!(read_pcd(&file[..file.len() - 1]), Err(PcdError::Truncated { .. })));
        // A huge POINTS count with a tiny stream must fail without allocating gigabytes.
        let mut huge = header("x y z _", "4 4 4 1", "F F F U", "1 1 1 2", 200_000_000, "binary_compressed");
        huge.extend_from_slice(&[2, 0, 0, 0, 0x00, 0x9c, 0xe4, 0xa6, 0, 7]); // 2 packed bytes, 2.8e9 unpacked
        assert!(matches!(read_pcd(&huge), Err(PcdError::Lzf(LzfError::TooShort { .. }))));
        let bad = compressed_file(&pts, &[0x20, 0x05], raw.len());
        assert!(matches!(read_pcd(&bad), Err(PcdError::Lzf(LzfError::BadBackReference { .. }))));
    }

    #[test]
    fn header_errors_are_precise() {
        let msg = |b: &[u8]| read_pcd(b).unwrap_err().to_string();
        assert_eq!(
            msg(b"VERSION 0.7\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n"),
            "PCD header: missing FIELDS line"
        );
        assert_eq!(
            msg(&header("x y intensity", "4 4 4", "F F F", "1 1 1", 1, "ascii")),
            "PCD: no x/y/z fields (field 'z' not found)"
        );
        assert!(msg(&header("x y z", "4 4 4", "F F U", "1 1 1", 1, "ascii")).contains("must be F4 or F8"));
        assert!(msg(&header("x y z", "4 4", "F F F", "1 1 1", 1, "binary")).contains("SIZE has 2"));
        assert!(
            msg(&header("x y z", "4 4 4", "F F F", "1 1 1", 1, "lzma")).contains("unsupported DATA mode")
        );
        let mismatch = String::from_utf8(header("x y z", "4 4 4", "F F F", "1 1 1", 4, "ascii")).unwrap();
        assert_eq!(
            msg(mismatch.replace("POINTS 4", "POINTS 5").as_bytes()),
            "PCD header: POINTS 5 does not equal WIDTH 4 × HEIGHT 1"
        );
        assert_eq!(msg(b"FIELDS x y z\n"), "PCD header: missing DATA line");
        assert!(msg(b"FIELDS x y z\nBOGUS 1\nDATA ascii\n").contains("line 2: unknown keyword 'BOGUS'"));
        assert!(msg(&b"# c\n".repeat(2000)).contains("no DATA line within"));
        assert!(msg(b"VIEWPOINT 1 2 3\n").contains("VIEWPOINT needs 7 finite numbers"));
    }

    #[test]
    fn ascii_errors() {
        let mut short = header("x y z", "4 4 4", "F F F", "1 1 1", 3, "ascii");
        short.extend_from_slice(b"1 2 3\n\n4 5 6\n");
        assert_eq!(
            read_pcd(&short).unwrap_err().to_string(),
            "PCD data: expected 3 ascii points, found 2 (file truncated?)"
        );
        let mut bad = header("x y z", "4 4 4", "F F F", "1 1 1", 1, "ascii");
        bad.extend_from_slice(b"1 two 3\n");
        assert_eq!(read_pcd(&bad).unwrap_err().to_string(), "PCD data: ascii line 1: invalid number 'two'");
    }

    fn valid_files() -> Vec<Vec<u8>> {
        let pts: Vec<[f32; 3]> = (0..20).map(|i| [i as f32, 0.5, -1.0]).collect();
        let raw = soa(&pts);
        vec![
            write_pcd_binary(&pts, VP),
            write_pcd_ascii(&pts, VP),
            compressed_file(&pts, &lzf::compress(&raw), raw.len()),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn random_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..400)) {
            let _ = read_pcd(&data);
            let mut with_header = header("x y z", "4 4 4", "F F F", "1 1 1", 3, "binary_compressed");
            with_header.extend_from_slice(&data);
            let _ = read_pcd(&with_header);
        }

        #[test]
        fn truncations_and_mutations_never_panic(which in 0usize..3, cut in any::<prop::sample::Index>(),
                                                 flip in any::<prop::sample::Index>(), byte in any::<u8>()) {
            // (An ascii file cut inside its last line can still be valid, so only binary ones must fail.)
            let file = &valid_files()[which];
            let n = cut.index(file.len() + 1);
            if n < file.len() && which != 1 {
                prop_assert!(read_pcd(&file[..n]).is_err());
            }
            let mut mutated = file.clone();
            mutated[flip.index(file.len())] = byte;
            let _ = read_pcd(&mutated);
        }
    }
}
