//! Solid primitives and their exact geometry: ray intervals, containment, signed distance and
//! cell overlap.
//!
//! Every solid is a closed set (its boundary belongs to it). All arithmetic is plain IEEE f64
//! (`+ − × ÷ sqrt`), so results are bit-identical on every machine.

/// One solid primitive of a [`Scene`](super::Scene). Cylinders stand upright (axis along z).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Solid {
    /// An axis-aligned box `min ≤ p ≤ max` (metres).
    Aabb { min: [f64; 3], max: [f64; 3] },
    /// An upright cylinder: `|p.xy − centre_xy| ≤ radius` and `z_min ≤ p.z ≤ z_max`.
    Cylinder { centre_xy: [f64; 2], radius: f64, z_min: f64, z_max: f64 },
    /// A ball `|p − centre| ≤ radius`.
    Sphere { centre: [f64; 3], radius: f64 },
}

/// Tolerance (metres) below which an overlap of a cell with a solid counts as touching only.
/// It absorbs the rounding of `key · res` when a solid's face lies on a grid plane.
pub(crate) const OVERLAP_EPS_M: f64 = 1e-9;

impl Solid {
    /// The axis-aligned bounding box `(min, max)` of the solid.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match *self {
            Solid::Aabb { min, max } => (min, max),
            Solid::Cylinder { centre_xy: c, radius: r, z_min, z_max } => {
                ([c[0] - r, c[1] - r, z_min], [c[0] + r, c[1] + r, z_max])
            }
            Solid::Sphere { centre: c, radius: r } => {
                ([c[0] - r, c[1] - r, c[2] - r], [c[0] + r, c[1] + r, c[2] + r])
            }
        }
    }

    /// Whether `p` lies in the solid (boundary included).
    pub fn contains(&self, p: [f64; 3]) -> bool {
        match *self {
            Solid::Aabb { min, max } => (0..3).all(|i| min[i] <= p[i] && p[i] <= max[i]),
            Solid::Cylinder { centre_xy: c, radius: r, z_min, z_max } => {
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                z_min <= p[2] && p[2] <= z_max && dx * dx + dy * dy <= r * r
            }
            Solid::Sphere { centre: c, radius: r } => norm2(sub(p, c)) <= r * r,
        }
    }

    /// Exact Euclidean signed distance from `p` to the solid's surface: positive outside,
    /// negative inside, zero on the boundary.
    pub fn signed_distance(&self, p: [f64; 3]) -> f64 {
        match *self {
            Solid::Aabb { min, max } => {
                let q = [0, 1, 2].map(|i| {
                    let centre = 0.5 * (min[i] + max[i]);
                    let half = 0.5 * (max[i] - min[i]);
                    (p[i] - centre).abs() - half
                });
                combine_sdf(&q)
            }
            Solid::Cylinder { centre_xy: c, radius: r, z_min, z_max } => {
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                let radial = (dx * dx + dy * dy).sqrt() - r;
                let axial = (p[2] - 0.5 * (z_min + z_max)).abs() - 0.5 * (z_max - z_min);
                combine_sdf(&[radial, axial])
            }
            Solid::Sphere { centre: c, radius: r } => norm2(sub(p, c)).sqrt() - r,
        }
    }

    /// The closed interval of line parameters `t` (over all reals) for which `origin + t·dir`
    /// lies in the solid, or `None` when the line misses it. `dir` need not be unit length but
    /// must be non-zero and finite.
    pub(crate) fn line_interval(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<(f64, f64)> {
        match *self {
            Solid::Aabb { min, max } => {
                let mut iv = (f64::NEG_INFINITY, f64::INFINITY);
                for i in 0..3 {
                    iv = intersect(iv, slab(origin[i], dir[i], min[i], max[i])?)?;
                }
                Some(iv)
            }
            Solid::Cylinder { centre_xy: c, radius: r, z_min, z_max } => {
                let z = slab(origin[2], dir[2], z_min, z_max)?;
                let (px, py) = (origin[0] - c[0], origin[1] - c[1]);
                let a = dir[0] * dir[0] + dir[1] * dir[1];
                let c0 = px * px + py * py - r * r;
                let radial = if a == 0.0 {
                    // Vertical line: inside the infinite cylinder everywhere or nowhere.
                    if c0 <= 0.0 { (f64::NEG_INFINITY, f64::INFINITY) } else { return None }
                } else {
                    quadratic_interval(a, px * dir[0] + py * dir[1], c0)?
                };
                intersect(z, radial)
            }
            Solid::Sphere { centre: c, radius: r } => {
                let p = sub(origin, c);
                let a = norm2(dir);
                if a == 0.0 {
                    return None;
                }
                quadratic_interval(a, dot(p, dir), norm2(p) - r * r)
            }
        }
    }

    /// Whether the solid and the closed box `[lo, hi]` share a region of positive volume (faces,
    /// edges or points merely touching do not count, up to [`OVERLAP_EPS_M`]).
    pub(crate) fn overlaps_box(&self, lo: [f64; 3], hi: [f64; 3]) -> bool {
        let e = OVERLAP_EPS_M;
        let open = |a_min: f64, a_max: f64, b_min: f64, b_max: f64| a_min < b_max - e && a_max > b_min + e;
        match *self {
            Solid::Aabb { min, max } => (0..3).all(|i| open(min[i], max[i], lo[i], hi[i])),
            Solid::Cylinder { centre_xy: c, radius: r, z_min, z_max } => {
                if !open(z_min, z_max, lo[2], hi[2]) || r <= e {
                    return false;
                }
                let dx = c[0] - c[0].clamp(lo[0], hi[0]);
                let dy = c[1] - c[1].clamp(lo[1], hi[1]);
                let re = r - e;
                dx * dx + dy * dy < re * re
            }
            Solid::Sphere { centre: c, radius: r } => {
                if r <= e {
                    return false;
                }
                let d = [0, 1, 2].map(|i| c[i] - c[i].clamp(lo[i], hi[i]));
                let re = r - e;
                norm2(d) < re * re
            }
        }
    }
}

/// Signed distance from per-axis excesses `q` (|p − centre| − half-extent, or the radial /
/// axial equivalents): the length of the positive part outside, the largest excess inside.
fn combine_sdf(q: &[f64]) -> f64 {
    let outside = q.iter().map(|v| v.max(0.0) * v.max(0.0)).sum::<f64>().sqrt();
    let inside = q.iter().copied().fold(f64::NEG_INFINITY, f64::max).min(0.0);
    outside + inside
}

/// The parameter interval in which `o + t·d` lies between `lo` and `hi` along one axis.
pub(crate) fn slab(o: f64, d: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
    if d == 0.0 {
        if o < lo || o > hi { None } else { Some((f64::NEG_INFINITY, f64::INFINITY)) }
    } else {
        // Division (not multiplication by 1/d) so a tiny `d` cannot turn 0·∞ into NaN.
        let t0 = (lo - o) / d;
        let t1 = (hi - o) / d;
        Some((t0.min(t1), t0.max(t1)))
    }
}

pub(crate) fn intersect(a: (f64, f64), b: (f64, f64)) -> Option<(f64, f64)> {
    let lo = a.0.max(b.0);
    let hi = a.1.min(b.1);
    (lo <= hi).then_some((lo, hi))
}

/// The interval between the real roots of `a·t² + 2·hb·t + c` (`a > 0`), where it is ≤ 0, using
/// the cancellation-free form of the quadratic formula.
fn quadratic_interval(a: f64, hb: f64, c: f64) -> Option<(f64, f64)> {
    let disc = hb * hb - a * c;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let q = if hb >= 0.0 { -(hb + s) } else { s - hb };
    if q == 0.0 {
        // hb = 0 and disc = 0, hence c = 0: a double root at t = 0.
        return Some((0.0, 0.0));
    }
    let (r1, r2) = (q / a, c / q);
    Some((r1.min(r2), r1.max(r2)))
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn norm2(a: [f64; 3]) -> f64 {
    dot(a, a)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn first_hit(s: &Solid, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
        let (t0, t1) = s.line_interval(o, d)?;
        (t1 >= 0.0).then_some(t0.max(0.0))
    }

    #[test]
    fn box_signed_distance_outside_inside_and_corner() {
        let b = Solid::Aabb { min: [0.0, 0.0, 0.0], max: [2.0, 2.0, 2.0] };
        assert_eq!(b.signed_distance([1.0, 1.0, 1.0]), -1.0);
        assert_eq!(b.signed_distance([1.0, 1.0, 3.0]), 1.0);
        assert_eq!(b.signed_distance([3.0, 3.0, 1.0]), 2f64.sqrt());
        assert_eq!(b.signed_distance([1.0, 0.0, 1.0]), 0.0);
    }

    #[test]
    fn cylinder_signed_distance_side_cap_and_rim() {
        let c = Solid::Cylinder { centre_xy: [0.0, 0.0], radius: 1.0, z_min: 0.0, z_max: 2.0 };
        assert_eq!(c.signed_distance([3.0, 0.0, 1.0]), 2.0);
        assert_eq!(c.signed_distance([0.0, 0.0, 5.0]), 3.0);
        assert_eq!(c.signed_distance([0.0, 0.0, 1.5]), -0.5);
        assert_eq!(c.signed_distance([4.0, 0.0, 6.0]), 5.0);
    }

    #[test]
    fn sphere_interval_is_symmetric_chord() {
        let s = Solid::Sphere { centre: [3.0, 0.0, 0.0], radius: 1.0 };
        let (t0, t1) = s.line_interval([0.0, 0.6, 0.0], [1.0, 0.0, 0.0]).expect("chord");
        assert!((t0 - 2.2).abs() < 1e-12 && (t1 - 3.8).abs() < 1e-12, "{t0} {t1}");
        assert_eq!(s.line_interval([0.0, 1.5, 0.0], [1.0, 0.0, 0.0]), None);
    }

    #[test]
    fn vertical_ray_through_cylinder_hits_cap() {
        let c = Solid::Cylinder { centre_xy: [0.0, 0.0], radius: 1.0, z_min: 0.0, z_max: 2.0 };
        assert_eq!(first_hit(&c, [0.5, 0.0, 10.0], [0.0, 0.0, -1.0]), Some(8.0));
        assert_eq!(first_hit(&c, [1.5, 0.0, 10.0], [0.0, 0.0, -1.0]), None);
    }

    #[test]
    fn overlap_ignores_touching_faces_but_counts_slivers_of_a_disc() {
        let b = Solid::Aabb { min: [0.0, 0.0, 0.0], max: [1.0, 1.0, 1.0] };
        assert!(!b.overlaps_box([1.0, 0.0, 0.0], [2.0, 1.0, 1.0]));
        assert!(b.overlaps_box([0.9, 0.9, 0.9], [2.0, 2.0, 2.0]));
        let c = Solid::Cylinder { centre_xy: [0.0, 0.0], radius: 1.0, z_min: 0.0, z_max: 1.0 };
        // The cell's nearest corner (0.7, 0.7) is 0.99 m from the axis: a sliver overlaps.
        assert!(c.overlaps_box([0.7, 0.7, 0.2], [0.8, 0.8, 0.3]));
        assert!(!c.overlaps_box([0.71, 0.71, 0.2], [0.8, 0.8, 0.3]));
        assert!(!c.overlaps_box([0.0, 0.0, 1.0], [0.1, 0.1, 1.1]));
    }
}
