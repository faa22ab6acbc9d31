use bgkmap::core::{Integrator, MapParams};
use bgkmap::core::evidence::Scatter;
fn main() {
    let params = MapParams::default();
    let mut integ = Integrator::new(params);
    let b = std::fs::read("../shared/data/la3dm/sim_structured/sim_structured_12.pcd").unwrap();
    let c = bgkmap::io::pcd::read_pcd(&b).unwrap();
    let vp = c.viewpoint.unwrap();
    let set = integ.training(&c.points, [vp[0], vp[1], vp[2]]).clone();
    let geo = *integ.geometry();
    let table = integ.table().clone();
    println!("pairs {}", count_pairs(&set, 0.1, 0.2));
    let mut sc = Scatter::default();
    for _ in 0..10 {
        let t0 = std::time::Instant::now();
        let d = sc.delta(&set, &geo, &table);
        let ts = t0.elapsed();
        println!("scatter {ts:?} {}", d.blocks.len());
        sc.recycle(d);
    }
}
#[allow(dead_code)]
fn count_pairs(set: &bgkmap::core::training::TrainingSet, res: f64, ell: f64) -> usize {
    let l = ell / res;
    let mut n = 0;
    for p in set.hits.iter().chain(&set.frees) {
        let q = [p[0] / res, p[1] / res, p[2] / res];
        let c = q.map(|v| v.floor() as i32);
        for z in -3..=3 { for y in -3..=3 { for x in -3..=3 {
            let d = [c[0] + x, c[1] + y, c[2] + z];
            let dd: f64 = (0..3).map(|i| { let v = d[i] as f64 + 0.5 - q[i]; v * v }).sum();
            if dd < l * l { n += 1; }
        }}}
    }
    n
}
