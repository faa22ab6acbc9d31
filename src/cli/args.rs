//! Argument groups shared by several subcommands, and small helpers.

use crate::core::{MapParams, RangeMode, Thresholds};
use crate::io::pcd::read_pcd;
use crate::io::scan::{PointFrame, Scan, scan_from_pcd};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

/// Every map parameter as a flag; defaults are la3dm's (see `MapParams`).
#[derive(Debug, Clone, Args)]
pub struct ParamArgs {
    /// Cell edge (m).
    #[arg(long, default_value_t = 0.1, allow_negative_numbers = true)]
    pub resolution: f64,
    /// Kernel amplitude σ0.
    #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
    pub sf2: f64,
    /// Kernel length and support radius (m).
    #[arg(long, default_value_t = 0.2, allow_negative_numbers = true)]
    pub ell: f64,
    /// Free-space sample spacing along each ray (m).
    #[arg(long, default_value_t = 0.5, allow_negative_numbers = true)]
    pub free_resolution: f64,
    /// Downsampling voxel edge for hits and free samples (m).
    #[arg(long, default_value_t = 0.1, allow_negative_numbers = true)]
    pub ds_resolution: f64,
    /// Maximum range (m); 0 = unlimited.
    #[arg(long, default_value_t = 8.0, allow_negative_numbers = true)]
    pub max_range: f64,
    /// Hits beyond max range: `truncate` (free ray up to max range) or `drop` (la3dm).
    #[arg(long, default_value = "truncate")]
    pub range_mode: RangeMode,
    /// Prior pseudo-count α0.
    #[arg(long, default_value_t = 0.001, allow_negative_numbers = true)]
    pub prior_a: f64,
    /// Prior pseudo-count β0.
    #[arg(long, default_value_t = 0.001, allow_negative_numbers = true)]
    pub prior_b: f64,
    /// Do not add the sensor origin as a free sample.
    #[arg(long)]
    pub no_origin_free: bool,
    /// Place training points at the centres of SUB_CELLS³ sub-cells per cell (a power of two
    /// up to 64; at most res/(2·SUB_CELLS) off per axis; 0 = exactly where they are).
    #[arg(long, default_value_t = 8)]
    pub sub_cells: u32,
    #[command(flatten)]
    pub thresholds: ThresholdArgs,
}

impl ParamArgs {
    pub fn to_params(&self) -> Result<MapParams> {
        let p = MapParams {
            resolution_m: self.resolution,
            sf2: self.sf2,
            ell_m: self.ell,
            free_resolution_m: self.free_resolution,
            ds_resolution_m: self.ds_resolution,
            max_range_m: self.max_range,
            range_mode: self.range_mode,
            prior_a: self.prior_a,
            prior_b: self.prior_b,
            origin_as_free: !self.no_origin_free,
            sub_cells: self.sub_cells,
            thresholds: self.thresholds.resolve(Thresholds::default())?,
        };
        p.validate()?;
        Ok(p)
    }
}

/// State thresholds; unset ones fall back to the map's defaults.
#[derive(Debug, Clone, Args)]
pub struct ThresholdArgs {
    /// Free when p < P_FREE.
    #[arg(long, allow_negative_numbers = true)]
    pub p_free: Option<f64>,
    /// Occupied when p > P_OCC.
    #[arg(long, allow_negative_numbers = true)]
    pub p_occ: Option<f64>,
    /// A state needs variance < VAR_MAX.
    #[arg(long, allow_negative_numbers = true)]
    pub var_max: Option<f64>,
}

impl ThresholdArgs {
    pub fn resolve(&self, defaults: Thresholds) -> Result<Thresholds> {
        let t = Thresholds {
            p_free: self.p_free.unwrap_or(defaults.p_free),
            p_occ: self.p_occ.unwrap_or(defaults.p_occ),
            var_max: self.var_max.unwrap_or(defaults.var_max),
        };
        t.validate()?;
        Ok(t)
    }
}

/// How PCD inputs are read.
#[derive(Debug, Clone, Args)]
pub struct ScanArgs {
    /// Frame of the points: `world` (VIEWPOINT gives only the origin) or `sensor`.
    #[arg(long, default_value = "world", value_parser = parse_frame)]
    pub frame: PointFrame,
    /// Sensor origin X,Y,Z (m) for files without VIEWPOINT (overrides VIEWPOINT's translation).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub origin: Option<[f64; 3]>,
}

fn parse_frame(s: &str) -> Result<PointFrame, String> {
    match s {
        "world" => Ok(PointFrame::World),
        "sensor" => Ok(PointFrame::Sensor),
        _ => Err(format!("unknown frame {s:?} (world|sensor)")),
    }
}

/// Parses `x,y,z`.
pub fn parse_vec3(s: &str) -> Result<[f64; 3], String> {
    let v = parse_floats(s, 3)?;
    Ok([v[0], v[1], v[2]])
}

/// Parses `n` comma-separated finite numbers.
pub fn parse_floats(s: &str, n: usize) -> Result<Vec<f64>, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("not a number: {t:?}")))
        .collect::<Result<_, _>>()?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        return Err(format!("expected {n} finite comma-separated numbers, got {s:?}"));
    }
    Ok(v)
}

/// Reads one PCD file into a world-frame scan.
pub fn load_scan(path: &Path, args: &ScanArgs) -> Result<Scan> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let cloud = read_pcd(&bytes).with_context(|| format!("{}", path.display()))?;
    let scan =
        scan_from_pcd(cloud, args.frame, args.origin).with_context(|| format!("{}", path.display()))?;
    if scan.points_world.is_empty() {
        bail!("{}: the scan has no finite points", path.display());
    }
    Ok(scan)
}

/// Reads one PCD file as the raw scan a map journals: points in the given frame as stored in the
/// file, pose = VIEWPOINT (translation replaced by `--origin`), identity rotation when the file
/// has none. Returns it with the number of non-finite points dropped.
pub fn load_raw_scan(path: &Path, args: &ScanArgs) -> Result<(crate::core::RawScan, usize)> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let cloud = read_pcd(&bytes).with_context(|| format!("{}", path.display()))?;
    let vp = cloud.viewpoint;
    let translation_m = match (args.origin, vp) {
        (Some(o), _) => o,
        (None, Some(v)) => [v[0], v[1], v[2]],
        (None, None) => bail!(
            "{}: no sensor origin: the PCD file has no VIEWPOINT line (give --origin X,Y,Z)",
            path.display()
        ),
    };
    let rotation_wxyz = vp.map_or([1.0, 0.0, 0.0, 0.0], |v| [v[3], v[4], v[5], v[6]]);
    let pose = crate::core::Pose { translation_m, rotation_wxyz };
    pose.validate().with_context(|| format!("{}: VIEWPOINT", path.display()))?;
    if cloud.points.is_empty() {
        bail!("{}: the scan has no finite points", path.display());
    }
    let raw = crate::core::RawScan {
        frame: args.frame,
        world_from_sensor: pose,
        points: cloud.points,
        max_range_m: None,
    };
    Ok((raw, cloud.dropped_nonfinite))
}

/// Writes `bytes` to `path` atomically (temporary sibling + rename), or to stdout for `None`
/// (a reader that closes the pipe early, as `head` does, is not an error).
pub fn write_output(path: Option<&PathBuf>, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    match path {
        None => {
            let mut out = std::io::stdout().lock();
            match out.write_all(bytes).and_then(|()| out.flush()) {
                // The reader stopped reading (`| head`): what it read is all it asked for.
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
                r => r.context("writing to stdout"),
            }
        }
        Some(p) => {
            let tmp = crate::store::temp_sibling(p);
            let r = std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, p));
            if r.is_err() {
                let _ = std::fs::remove_file(&tmp);
            }
            r.with_context(|| format!("{}: cannot write", p.display()))
        }
    }
}

/// A progress bar on stderr (hidden when stderr is not a terminal).
pub fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    let style = indicatif::ProgressStyle::with_template("{msg:>10} [{bar:40}] {pos}/{len} {elapsed_precise}")
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style.progress_chars("=> "));
    bar.set_message(what.to_string());
    bar
}
