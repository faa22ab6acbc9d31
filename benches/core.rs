//! criterion micro-benchmarks of the core: the kernel, training-data generation, the evidence
//! scatter and ray traversal (plus a point query), on the built-in simulated room.
//! Run: `cargo bench --bench core` (CI only builds them: `cargo bench --no-run`).

use bgkmap::core::integrate::kernel::{KernelTable, unit_kernel};
use bgkmap::core::integrate::training::TrainingBuilder;
use bgkmap::core::integrate::{cell_points::PairGeometry, scatter::Scatter};
use bgkmap::core::query::{StopAt, cast_ray, query_points, traverse};
use bgkmap::core::{EvidenceMap, Integrator, MapParams};
use bgkmap::sim::{Lidar, simulate};
use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn kernel(c: &mut Criterion) {
    let table = KernelTable::new();
    let d: Vec<f64> = (0..1000).map(|i| f64::from(i) * 2e-4).collect();
    c.bench_function("kernel/unit_kernel_1000", |b| {
        b.iter(|| d.iter().map(|&x| unit_kernel(black_box(x), 0.2)).sum::<f64>())
    });
    c.bench_function("kernel/table_quantized_1000", |b| {
        b.iter(|| d.iter().map(|&x| table.quantized(black_box(x / 0.2))).sum::<i64>())
    });
}

fn scan_pipeline(c: &mut Criterion) {
    let params = MapParams::default();
    let (_, scans) = simulate(0, 2, &Lidar::default());
    let s = &scans[0];
    let mut builder = TrainingBuilder::default();
    c.bench_function("training/room_scan", |b| {
        b.iter(|| builder.build(black_box(&s.points_world), s.origin, &params).len())
    });
    let set = TrainingBuilder::default().build(&s.points_world, s.origin, &params);
    let geo = PairGeometry::of(&params);
    let table = KernelTable::new();
    let mut scatter = Scatter::default();
    c.bench_function("evidence/room_scan_scatter", |b| {
        b.iter(|| {
            let d = scatter.delta(black_box(&set), &geo, &table);
            let n = d.blocks.len();
            scatter.recycle(d);
            n
        })
    });
}

fn queries(c: &mut Criterion) {
    let params = MapParams::default();
    let (_, scans) = simulate(0, 12, &Lidar::default());
    let mut map = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    for s in &scans {
        integ.integrate(&mut map, &s.points_world, s.origin, 1);
    }
    let th = params.thresholds;
    let dirs = Lidar::default().directions(0.1);
    let o = scans[0].origin;
    c.bench_function("ray/traverse_8m_cells", |b| {
        b.iter(|| traverse(black_box(o), dirs[7], 8.0, params.resolution_m).len())
    });
    c.bench_function("ray/cast_360_rays_8m", |b| {
        b.iter(|| {
            dirs.iter()
                .step_by(16)
                .filter(|d| cast_ray(&map, o, **d, 8.0, StopAt::Occupied, &th).is_ok())
                .count()
        })
    });
    let pts: Vec<[f64; 3]> = scans[1].points_world.iter().map(|p| p.map(f64::from)).collect();
    c.bench_function("query/points_room_scan", |b| b.iter(|| query_points(&map, black_box(&pts), &th).len()));
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = kernel, scan_pipeline, queries
}
criterion_main!(benches);
