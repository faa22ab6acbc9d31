use super::*;
use crate::core::integrate::free_space::{along, free_samples};
use crate::core::integrate::voxel_table::{KEY_LIMIT, Slot, VoxelCentroids};
use crate::core::params::RangeMode;

fn params(max_range_m: f64, mode: RangeMode) -> MapParams {
    MapParams { max_range_m, range_mode: mode, ..Default::default() }
}

#[test]
fn free_samples_stop_where_a_sample_by_sample_loop_does() {
    // Lengths at, just below and just above multiples of the spacing (where the count's
    // estimate and the test `i·fr < len` can disagree), zero, tiny, and not a number.
    let plain = |o: [f64; 3], n: [f64; 3], len: f64, fr: f64| {
        let mut out = Vec::new();
        let mut i = 1u32;
        while f64::from(i) * fr < len {
            out.push(along(o, n, f64::from(i) * fr));
            i += 1;
        }
        if len > fr {
            out.push(along(o, n, len - fr));
        }
        out
    };
    let (o, n) = ([1.0, -2.0, 0.5], [0.6, 0.0, 0.8]);
    let mut cases = vec![0.0, 1e-300, f64::NAN, -1.0];
    for fr in [0.5, 0.1, 0.3, 0.7] {
        for k in 0..200 {
            let len = f64::from(k) * fr;
            cases.extend([len, len.next_down(), len.next_up(), len + 0.5 * fr]);
        }
        for &len in &cases {
            let mut out = vec![[9.0; 3]];
            free_samples(&mut out, o, n, len, fr);
            let want = plain(o, n, len, fr);
            assert_eq!(
                out[1..].iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>(),
                want.iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>(),
                "length {len:e}, spacing {fr}"
            );
        }
    }
}

#[test]
fn free_samples_follow_la3dm_spacing() {
    // One hit at 2.01 m along x: samples at 0.5, 1.0, 1.5, 2.0 and the extra one at 1.51.
    let mut b = TrainingBuilder::default();
    let p = MapParams { ds_resolution_m: 0.001, origin_as_free: false, ..params(0.0, RangeMode::Drop) };
    let t = b.build(&[[2.01, 0.0, 0.0]], [0.0, 0.0, 0.0], &p);
    assert_eq!(t.hits.len(), 1);
    let mut xs: Vec<f64> = t.frees.iter().map(|f| f[0]).collect();
    xs.sort_by(f64::total_cmp);
    let want = [0.5, 1.0, 1.5, 1.51, 2.0];
    assert_eq!(xs.len(), want.len());
    for (x, w) in xs.iter().zip(want) {
        assert!((x - w).abs() < 1e-6, "{xs:?}");
    }
}

#[test]
fn range_modes() {
    let mut b = TrainingBuilder::default();
    let pts = [[10.0f32, 0.05, 0.05]];
    let drop = b.build(&pts, [0.05, 0.05, 0.05], &params(8.0, RangeMode::Drop));
    assert!(drop.hits.is_empty());
    assert_eq!(drop.frees.len(), 1, "only the origin");
    let trunc = b.build(&pts, [0.05, 0.05, 0.05], &params(8.0, RangeMode::Truncate));
    assert!(trunc.hits.is_empty());
    assert_eq!(trunc.beyond_range, 1);
    let max_x = trunc.frees.iter().map(|f| f[0]).fold(f64::MIN, f64::max);
    assert!(max_x < 8.05 && max_x > 7.5, "free samples stop short of max range: {max_x}");
}

#[test]
fn non_finite_points_are_dropped_and_counted() {
    let mut b = TrainingBuilder::default();
    let t = b.build(
        &[[f32::NAN, 0.0, 0.0], [1.0, f32::INFINITY, 0.0], [1.0, 1.0, 1.0]],
        [0.0; 3],
        &MapParams::default(),
    );
    assert_eq!(t.dropped_points, 2);
    assert_eq!(t.hits.len(), 1);
}

/// Rays near the end of the voxel key range take the range-tested path, and their samples
/// beyond it are left out: the training set equals one built by adding every sample with
/// its range test.
#[test]
fn rays_near_the_key_range_limit() {
    let edge = KEY_LIMIT * 0.1;
    let params = MapParams { max_range_m: 0.0, ..Default::default() };
    // A sensor just beyond the range (its first samples are too), one just inside it, one
    // near the other end, and one at home.
    for origin in [[edge + 1.0, 0.0, 0.0], [edge - 4.0, 0.0, 0.0], [-edge + 1.0, 3.0, -2.0], [1.0, 2.0, 3.0]]
    {
        let toward = if origin[0] > 0.0 { -1.0 } else { 1.0 };
        let pts: Vec<[f32; 3]> = (0..200)
            .map(|i| {
                let a = f64::from(i) * 0.031;
                [origin[0] + toward * (3.0 + a.cos()), origin[1] + 3.5 * a.sin(), origin[2] + 0.3]
                    .map(|v| v as f32)
            })
            .collect();
        let got = TrainingBuilder::default().build(&pts, origin, &params);
        let (hits, frees, rejected) = ray_major_reference(&pts, origin, &params);
        assert_eq!(got.hits, hits, "origin {origin:?}");
        assert_eq!(sorted_bits(&got.frees), sorted_bits(&frees), "origin {origin:?}");
        assert_eq!(rejected > 0, origin[0] > edge, "samples beyond the key range, origin {origin:?}");
    }
}

/// The training set the plain way, every point through range-tested tables: hits, free
/// centroids (ray by ray, each ray's samples outward, the origin last) and the free
/// samples the table rejected.
fn ray_major_reference(
    pts: &[[f32; 3]],
    origin: [f64; 3],
    params: &MapParams,
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, usize) {
    let inv_ds = 1.0 / params.ds_resolution_m;
    let mut hits = VoxelCentroids::<Slot>::default();
    let raw: Vec<[f64; 3]> = pts.iter().map(|p| p.map(f64::from)).collect();
    hits.add_all::<true>(&raw, inv_ds);
    let mut centroids = Vec::new();
    hits.centroids_into(&mut centroids);
    let mut samples = Vec::new();
    let mut kept = Vec::new();
    for &h in &centroids {
        let v = [h[0] - origin[0], h[1] - origin[1], h[2] - origin[2]];
        let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let mut len = r;
        if params.max_range_m > 0.0 && r > params.max_range_m {
            match params.range_mode {
                RangeMode::Drop => continue,
                RangeMode::Truncate => len = params.max_range_m,
            }
        } else {
            kept.push(h);
        }
        free_samples(&mut samples, origin, v.map(|c| c / r), len, params.free_resolution_m);
    }
    if params.origin_as_free {
        samples.push(origin);
    }
    let mut frees = VoxelCentroids::<Slot>::default();
    let rejected = frees.add_all::<true>(&samples, inv_ds);
    let mut want = Vec::new();
    frees.centroids_into(&mut want);
    (kept, want, rejected)
}

/// Points as bit patterns, sorted: the multiset, for sets whose order is not a contract.
fn sorted_bits(points: &[[f64; 3]]) -> Vec<[u64; 3]> {
    let mut bits: Vec<[u64; 3]> = points.iter().map(|p| p.map(f64::to_bits)).collect();
    bits.sort_unstable();
    bits
}

/// Free samples shell by shell give every free voxel the same bits as ray by ray: random
/// scenes large enough for shells, around origins off the grid (negative coordinates too),
/// with rays ending anywhere in a shell, both range modes, with and without the origin as a
/// free sample, at sample spacings just above a voxel's diagonal and well above it; and
/// scans that keep to ray by ray (small, or spacing within the diagonal) are checked too.
#[test]
fn shells_give_the_ray_major_centroids() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut builder = TrainingBuilder::default();
    let mut shelled = 0;
    for case in 0..12 {
        let origin =
            [rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0), rng.random_range(-3.0..3.0)];
        let fr = [0.5, 0.18, 0.3, 0.15][case % 4];
        let params = MapParams {
            free_resolution_m: fr,
            max_range_m: [30.0, 0.0, 20.0][case % 3],
            range_mode: if case % 2 == 0 { RangeMode::Truncate } else { RangeMode::Drop },
            origin_as_free: case % 5 != 0,
            ..Default::default()
        };
        let n = if case == 5 { 40 } else { 2500 };
        // Cases 4 and 10 (unlimited range) have a hit 450 m out, whose shells span more
        // voxels than compact slots tell apart: they take full keys.
        let far = case == 4 || case == 10;
        let mut pts: Vec<[f32; 3]> = (0..n)
            .map(|_| {
                let d: [f64; 3] =
                    [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-0.3..0.3)];
                let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
                let r = rng.random_range(0.05..40.0);
                [0, 1, 2].map(|i| (origin[i] + d[i] / norm * r) as f32)
            })
            .collect();
        if far {
            pts.push([origin[0] + 450.0, origin[1] - 3.0, origin[2]].map(|v| v as f32));
        }
        let got = builder.build(&pts, origin, &params);
        let (hits, frees, rejected) = ray_major_reference(&pts, origin, &params);
        let shells = fr > 3f64.sqrt() * params.ds_resolution_m && n > 1000;
        assert_eq!(builder.by_shell, shells, "case {case}: path taken");
        assert_eq!(builder.compact_shells, shells && !far, "case {case}: slots");
        shelled += usize::from(builder.by_shell);
        assert_eq!(rejected, 0);
        assert_eq!(got.hits, hits, "case {case}");
        assert_eq!(got.frees.len(), frees.len(), "case {case}");
        assert_eq!(sorted_bits(&got.frees), sorted_bits(&frees), "case {case}");
    }
    assert_eq!(shelled, 8, "cases that went shell by shell");
}

#[test]
fn hits_are_voxel_centroids() {
    let mut b = TrainingBuilder::default();
    let t =
        b.build(&[[1.01, 1.01, 1.01], [1.03, 1.05, 1.07], [1.21, 1.0, 1.0]], [0.0; 3], &MapParams::default());
    assert_eq!(t.hits.len(), 2);
    assert!((t.hits[0][0] - 1.02).abs() < 1e-6 && (t.hits[0][2] - 1.04).abs() < 1e-6);
}

/// algorithm.md §4: the exact training-set sizes of la3dm's semantics on the sample data
/// (ds 0.1, fr 0.5, max range 8, rays beyond range dropped).
#[test]
#[cfg_attr(not(bgkmap_sample_data), ignore = "needs the sample data ../shared/data/la3dm")]
fn sample_data_training_counts_match_la3dm() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/la3dm/sim_structured");
    let voxels = [1918, 1459, 446, 544, 1414, 1733, 1737, 1919, 1587, 1398, 1779, 2162];
    let kept = [1720, 1297, 446, 544, 1049, 1604, 1677, 1481, 1384, 1210, 1728, 1958];
    let total = [5546, 3966, 711, 1076, 3806, 4672, 4655, 6591, 4516, 4228, 4699, 6561];
    let params = params(8.0, RangeMode::Drop);
    let mut b = TrainingBuilder::default();
    for i in 0..12 {
        let bytes = std::fs::read(dir.join(format!("sim_structured_{}.pcd", i + 1))).unwrap();
        let cloud = crate::io::pcd::read_pcd(&bytes).unwrap();
        let v = cloud.viewpoint.unwrap();
        let t = b.build(&cloud.points, [v[0], v[1], v[2]], &params);
        assert_eq!((t.hit_voxels, t.hits.len(), t.len()), (voxels[i], kept[i], total[i]), "scan {}", i + 1);
    }
}
