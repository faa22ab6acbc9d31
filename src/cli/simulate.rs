//! `bgkmap simulate`: scans and ground truth of the built-in simulated room, as files.

use super::args::write_output;
use crate::io::octomap::{BtTree, write_bt};
use crate::io::pcd::write_pcd_binary;
use crate::sim::{Lidar, Scene, simulate};
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

/// Writes the scene's analytic ground truth at `res` as an OctoMap `.bt` (pruned).
pub fn write_truth(scene: &Scene, res: f64, path: &Path) -> Result<BtTree> {
    let tree = BtTree::from_cells(res, scene.truth_cells(res), true)?;
    write_output(Some(&path.to_path_buf()), &write_bt(&tree))?;
    Ok(tree)
}
