//! Scan records (encoding 1, documented in the parent module): a [`RawScan`] ⇄ bytes, and the
//! scan fingerprint (`scans.crc32`).

use crate::core::{PointFrame, Pose, RawScan};
use crate::io::lzf;

const ENCODING: u8 = 1;
const HEADER_BYTES: usize = 72;
const CODEC_RAW: u8 = 0;
const CODEC_XOR_SHUFFLE_LZF: u8 = 1;
const FLAG_MAX_RANGE: u8 = 1;

/// Encodes a scan record; points are compressed when that makes the record smaller.
pub fn encode_record(scan: &RawScan) -> Vec<u8> {
    let raw = raw_points(&scan.points);
    let packed = lzf::compress(&shuffle(&raw, scan.points.len()));
    let (codec, payload) =
        if packed.len() < raw.len() { (CODEC_XOR_SHUFFLE_LZF, packed) } else { (CODEC_RAW, raw) };
    let mut out = header(scan, codec);
    out.extend_from_slice(&payload);
    out
}

/// The scan fingerprint: CRC-32 of `source ‖ 0 ‖ seq (u64 LE) ‖ canonical record bytes`.
pub fn fingerprint(source: &str, seq: u64, scan: &RawScan) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(source.as_bytes());
    h.update(&[0]);
    h.update(&seq.to_le_bytes());
    h.update(&header(scan, CODEC_RAW));
    h.update(&raw_points(&scan.points));
    h.finalize()
}

fn header(scan: &RawScan, codec: u8) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + 12 * scan.points.len());
    let frame = match scan.frame {
        PointFrame::World => 0,
        PointFrame::Sensor => 1,
    };
    let flags = if scan.max_range_m.is_some() { FLAG_MAX_RANGE } else { 0 };
    out.extend_from_slice(&[ENCODING, frame, codec, flags]);
    for v in scan.world_from_sensor.translation_m.iter().chain(&scan.world_from_sensor.rotation_wxyz) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&scan.max_range_m.unwrap_or(0.0).to_le_bytes());
    out.extend_from_slice(&(scan.points.len() as u32).to_le_bytes());
    out
}

fn raw_points(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

/// XOR with the same axis of the previous point, then split the words into byte planes.
fn shuffle(raw: &[u8], n: usize) -> Vec<u8> {
    let values = 3 * n;
    let word = |i: usize| u32::from_le_bytes([raw[4 * i], raw[4 * i + 1], raw[4 * i + 2], raw[4 * i + 3]]);
    let mut out = vec![0u8; raw.len()];
    for i in 0..values {
        let d = if i < 3 { word(i) } else { word(i) ^ word(i - 3) };
        for (k, b) in d.to_le_bytes().into_iter().enumerate() {
            out[k * values + i] = b;
        }
    }
    out
}

fn unshuffle(s: &[u8], n: usize) -> Vec<[f32; 3]> {
    let values = 3 * n;
    let mut words = vec![0u32; values];
    for i in 0..values {
        let d = u32::from_le_bytes([s[i], s[values + i], s[2 * values + i], s[3 * values + i]]);
        words[i] = if i < 3 { d } else { d ^ words[i - 3] };
    }
    words
        .chunks_exact(3)
        .map(|w| [f32::from_bits(w[0]), f32::from_bits(w[1]), f32::from_bits(w[2])])
        .collect()
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[at..at + 8]);
    f64::from_le_bytes(w)
}

/// Decodes a scan record; the error says what is wrong.
pub fn decode_record(data: &[u8]) -> Result<RawScan, String> {
    if data.len() < HEADER_BYTES {
        return Err(format!("record of {} bytes is shorter than its {HEADER_BYTES}-byte header", data.len()));
    }
    if data[0] != ENCODING {
        return Err(format!("unknown record encoding {}", data[0]));
    }
    let frame = match data[1] {
        0 => PointFrame::World,
        1 => PointFrame::Sensor,
        f => return Err(format!("unknown frame {f}")),
    };
    if data[3] & !FLAG_MAX_RANGE != 0 {
        return Err(format!("unknown flags {:#04x}", data[3]));
    }
    let translation_m = [f64_at(data, 4), f64_at(data, 12), f64_at(data, 20)];
    let rotation_wxyz = [f64_at(data, 28), f64_at(data, 36), f64_at(data, 44), f64_at(data, 52)];
    let max_range_m = (data[3] & FLAG_MAX_RANGE != 0).then(|| f64_at(data, 60));
    let n = u32::from_le_bytes([data[68], data[69], data[70], data[71]]) as usize;
    let payload = &data[HEADER_BYTES..];
    let points = match data[2] {
        CODEC_RAW => {
            if payload.len() != 12 * n {
                return Err(format!("{} point bytes for {n} points", payload.len()));
            }
            payload
                .chunks_exact(12)
                .map(|c| {
                    let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                    [f(0), f(4), f(8)]
                })
                .collect()
        }
        CODEC_XOR_SHUFFLE_LZF => unshuffle(&lzf::decompress(payload, 12 * n).map_err(|e| e.to_string())?, n),
        c => return Err(format!("unknown points codec {c}")),
    };
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err("non-finite point".into());
    }
    Ok(RawScan { frame, world_from_sensor: Pose { translation_m, rotation_wxyz }, points, max_range_m })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(n: usize, max_range_m: Option<f64>) -> RawScan {
        let points = (0..n)
            .map(|i| {
                let a = i as f32 * 0.01;
                [3.0 * a.cos(), 3.0 * a.sin(), 0.5 + (i % 16) as f32 * 0.05]
            })
            .collect();
        let pose = Pose { translation_m: [1.5, -2.25, 0.5], rotation_wxyz: [0.6, 0.0, 0.0, 0.8] };
        RawScan { frame: PointFrame::Sensor, world_from_sensor: pose, points, max_range_m }
    }

    #[test]
    fn records_round_trip_bit_for_bit_and_compress() {
        for (n, r) in [(0, None), (1, Some(4.5)), (2, None), (3500, Some(8.0))] {
            let s = scan(n, r);
            let bytes = encode_record(&s);
            let back = decode_record(&bytes).unwrap();
            assert_eq!(back, s);
            if n == 3500 {
                assert_eq!(bytes[2], CODEC_XOR_SHUFFLE_LZF);
                assert!(bytes.len() < HEADER_BYTES + 12 * n * 9 / 10, "{} bytes", bytes.len());
            }
        }
    }

    #[test]
    fn fingerprint_ignores_the_codec_and_names_the_identity() {
        let s = scan(100, None);
        let f = fingerprint("r", 1, &s);
        assert_eq!(f, fingerprint("r", 1, &decode_record(&encode_record(&s)).unwrap()));
        assert_ne!(f, fingerprint("r", 2, &s));
        assert_ne!(f, fingerprint("q", 1, &s));
        let mut moved = s.clone();
        moved.points[7][1] = f32::from_bits(moved.points[7][1].to_bits() ^ 1);
        assert_ne!(f, fingerprint("r", 1, &moved));
    }

    #[test]
    fn garbage_is_refused_with_a_reason() {
        let good = encode_record(&scan(50, None));
        assert!(decode_record(&good[..10]).unwrap_err().contains("shorter"));
        let mut bad = good.clone();
        bad[0] = 9;
        assert!(decode_record(&bad).unwrap_err().contains("encoding"));
        let mut bad = good.clone();
        bad[2] = 7;
        assert!(decode_record(&bad).unwrap_err().contains("codec"));
        let mut bad = good.clone();
        bad.truncate(good.len() - 3);
        assert!(decode_record(&bad).is_err());
    }
}
