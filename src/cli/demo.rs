//! `bgkmap simulate` and `bgkmap demo`: the built-in simulated room, end to end.

use super::args::write_output;
use super::eval_cmd::evaluate;
use crate::core::{EvidenceMap, Integrator, MapParams};
use crate::io::octomap::{BtTree, write_bt};
use crate::io::pcd::write_pcd_binary;
use crate::sim::{Lidar, Scene, SimScan, simulate};
use crate::store::save_map;
use anyhow::{Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Scene and noise seed (0 = the fixed default room).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Number of scans along the robot's route.
    #[arg(long, default_value_t = 12)]
    pub scans: usize,
    /// Ground-truth resolution (m).
    #[arg(long, default_value_t = 0.1)]
    pub resolution: f64,
}

/// Writes `scan_NN.pcd` (world-frame points, VIEWPOINT = sensor origin) and `truth.bt`.
pub fn run_simulate(a: SimulateArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}: cannot create", a.out.display()))?;
    let (scene, scans) = simulate(a.seed, a.scans, &Lidar::default());
    for (i, s) in scans.iter().enumerate() {
        let vp = [s.origin[0], s.origin[1], s.origin[2], 1.0, 0.0, 0.0, 0.0];
        write_output(
            Some(&a.out.join(format!("scan_{:02}.pcd", i + 1))),
            &write_pcd_binary(&s.points_world, vp),
        )?;
    }
    write_truth(&scene, a.resolution, &a.out.join("truth.bt"))?;
    eprintln!("{}: {} scans and truth.bt (seed {})", a.out.display(), scans.len(), a.seed);
    Ok(())
}

fn write_truth(scene: &Scene, res: f64, path: &Path) -> Result<BtTree> {
    let tree = BtTree::from_cells(res, scene.truth_cells(res), true)?;
    write_output(Some(&path.to_path_buf()), &write_bt(&tree))?;
    Ok(tree)
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Working directory for the demo's map and truth.
    #[arg(long, default_value = "demo-data")]
    pub dir: PathBuf,
    /// Scans along the robot's route.
    #[arg(long, default_value_t = 24)]
    pub scans: usize,
}

/// Drives a simulated robot through the built-in room, builds the map, saves it and evaluates it.
pub fn run_demo(a: DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.dir).with_context(|| format!("{}: cannot create", a.dir.display()))?;
    let lidar = Lidar::default();
    let (scene, scans) = simulate(0, a.scans, &lidar);
    let params = MapParams::default();
    let mut map = EvidenceMap::new(params);
    let mut integrator = Integrator::new(params);
    let t0 = std::time::Instant::now();
    for s in &scans {
        integrate(&mut integrator, &mut map, s);
    }
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let map_path = a.dir.join("demo.bgkmap");
    let truth_path = a.dir.join("truth.bt");
    save_map(&map_path, &map)?;
    let truth = write_truth(&scene, params.resolution_m, &truth_path)?;
    let report = evaluate("demo", &map, &truth)?;
    println!("bgkmap demo: a robot with a 16-beam LiDAR drove through the built-in room");
    println!(
        "  {} scans ({} rays each) integrated in {ms:.1} ms ({:.3} ms per scan)",
        scans.len(),
        lidar.rays_per_scan(),
        ms / scans.len() as f64
    );
    println!(
        "  map: {} ({} cells with evidence in {} blocks)",
        map_path.display(),
        map.cells_with_evidence(),
        map.block_count()
    );
    println!(
        "  accuracy against the analytic ground truth: AUC {:.4} (unknown = 0.5), {:.4} on covered cells",
        report.all.auc, report.covered.auc
    );
    let (m, t) = (map_path.display(), truth_path.display());
    println!("\nTry:");
    println!("  bgkmap export {m} --format csv --box 2,2,0,3,3,1");
    println!("  bgkmap export {m} --format bt --out {}/demo.bt", a.dir.display());
    println!("  bgkmap eval {m} --truth {t} --roc {}/roc.png", a.dir.display());
    Ok(())
}

fn integrate(integrator: &mut Integrator, map: &mut EvidenceMap, s: &SimScan) {
    integrator.integrate(map, &s.points_world, s.origin, 1);
}
