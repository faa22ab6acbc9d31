//! Map parameters (fixed when a map is created) and per-query thresholds.
//!
//! Defaults are la3dm's HEAD configuration (docs/algorithm.md §8) except the range policy, where
//! bgkmap keeps no-return rays as free evidence (`RangeMode::Truncate`, docs/algorithm.md §6.2).

use std::fmt;

/// What happens to a hit farther than `max_range_m` from the sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RangeMode {
    /// The beam crossed `max_range_m` of free space: no hit, free samples up to `max_range_m`
    /// (what the sensor says, and what OctoMap does). The default.
    Truncate,
    /// The whole ray is discarded (la3dm's behaviour; for comparison).
    Drop,
}

impl RangeMode {
    pub fn as_str(self) -> &'static str {
        match self {
            RangeMode::Truncate => "truncate",
            RangeMode::Drop => "drop",
        }
    }
}

impl std::str::FromStr for RangeMode {
    type Err = ParamError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "truncate" => Ok(RangeMode::Truncate),
            "drop" => Ok(RangeMode::Drop),
            other => Err(ParamError::new("range_mode", format!("unknown mode {other:?} (truncate|drop)"))),
        }
    }
}

/// State thresholds of Eq. 9, chosen per query; never stored with evidence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    /// A cell is free when p < `p_free` (and the variance is below `var_max`). la3dm: 0.3.
    pub p_free: f64,
    /// A cell is occupied when p > `p_occ` (and the variance is below `var_max`). la3dm: 0.7.
    pub p_occ: f64,
    /// Maximum variance for a decided state. la3dm: 100, which is inert since Var ≤ 0.25.
    pub var_max: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Self { p_free: 0.3, p_occ: 0.7, var_max: 100.0 }
    }
}

impl Thresholds {
    pub fn validate(&self) -> Result<(), ParamError> {
        if !(self.p_free.is_finite() && (0.0..=1.0).contains(&self.p_free)) {
            return Err(ParamError::new("p_free", "must be within [0, 1]"));
        }
        if !(self.p_occ.is_finite() && (0.0..=1.0).contains(&self.p_occ)) {
            return Err(ParamError::new("p_occ", "must be within [0, 1]"));
        }
        if self.p_free > self.p_occ {
            return Err(ParamError::new("p_free", "must not exceed p_occ"));
        }
        if !(self.var_max.is_finite() && self.var_max >= 0.0) {
            return Err(ParamError::new("var_max", "must be finite and ≥ 0"));
        }
        Ok(())
    }
}

/// Everything that defines a map. Two maps merge only when these are equal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapParams {
    /// Cell edge in metres. la3dm: 0.1.
    pub resolution_m: f64,
    /// Kernel amplitude σ0 (a linear scale; applied when a cell is read). la3dm: 1.0.
    pub sf2: f64,
    /// Kernel length and support radius `l` in metres. la3dm: 0.2.
    pub ell_m: f64,
    /// Spacing of free-space samples along a ray, metres. la3dm: 0.5.
    pub free_resolution_m: f64,
    /// Voxel edge for downsampling hits and free samples, metres. la3dm: 0.1.
    pub ds_resolution_m: f64,
    /// Maximum sensor range in metres; 0 means unlimited. la3dm sample config: 8.
    pub max_range_m: f64,
    /// Policy for hits beyond `max_range_m`.
    pub range_mode: RangeMode,
    /// Prior pseudo-count α0. la3dm: 0.001.
    pub prior_a: f64,
    /// Prior pseudo-count β0. la3dm: 0.001.
    pub prior_b: f64,
    /// Add the sensor origin as one free sample per scan (la3dm adds it once per hit and
    /// averages; bgkmap adds it once).
    pub origin_as_free: bool,
    /// Training points are placed at the centre of their sub-cell, `sub_cells` per cell edge
    /// (a power of two up to [`MAX_SUB_CELLS`]; 0 keeps them where they are). At 8, a point
    /// moves at most 1/16 of a cell per axis (6.25 mm at 0.1 m, below any range sensor's
    /// noise), and every point's W³ kernel window is one of 8³ precomputed ones: evidence costs
    /// a third less. Maps written before this parameter existed read as 0.
    pub sub_cells: u32,
    /// Default state thresholds when a query gives none.
    pub thresholds: Thresholds,
}

impl Default for MapParams {
    fn default() -> Self {
        Self {
            resolution_m: 0.1,
            sf2: 1.0,
            ell_m: 0.2,
            free_resolution_m: 0.5,
            ds_resolution_m: 0.1,
            max_range_m: 8.0,
            range_mode: RangeMode::Truncate,
            prior_a: 0.001,
            prior_b: 0.001,
            origin_as_free: true,
            sub_cells: 8,
            thresholds: Thresholds::default(),
        }
    }
}

/// Largest kernel support in cells; bounds the work per training point (and memory per scan).
pub const MAX_ELL_IN_CELLS: f64 = 16.0;

/// Largest [`MapParams::sub_cells`].
pub const MAX_SUB_CELLS: u32 = 64;

impl MapParams {
    /// Checks every parameter; the error names the offending one.
    pub fn validate(&self) -> Result<(), ParamError> {
        let positive = |name: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ParamError::new(name, "must be finite and > 0"))
            }
        };
        positive("resolution", self.resolution_m)?;
        positive("sf2", self.sf2)?;
        positive("ell", self.ell_m)?;
        positive("free_resolution", self.free_resolution_m)?;
        positive("ds_resolution", self.ds_resolution_m)?;
        positive("prior_a", self.prior_a)?;
        positive("prior_b", self.prior_b)?;
        if !(self.resolution_m >= 1e-3) {
            return Err(ParamError::new("resolution", "must be at least 1 mm"));
        }
        if self.ell_m / self.resolution_m > MAX_ELL_IN_CELLS {
            return Err(ParamError::new("ell", format!("must be at most {MAX_ELL_IN_CELLS} cells")));
        }
        if !(self.max_range_m.is_finite() && self.max_range_m >= 0.0) {
            return Err(ParamError::new("max_range", "must be finite and ≥ 0 (0 = unlimited)"));
        }
        if self.free_resolution_m < self.resolution_m / 16.0 {
            return Err(ParamError::new("free_resolution", "must be at least resolution/16"));
        }
        if self.sub_cells > MAX_SUB_CELLS || !(self.sub_cells == 0 || self.sub_cells.is_power_of_two()) {
            return Err(ParamError::new(
                "sub_cells",
                format!("must be 0 (off) or a power of two up to {MAX_SUB_CELLS}, not {}", self.sub_cells),
            ));
        }
        self.thresholds.validate()
    }

    /// Lists the parameters that differ between two maps (for merge refusals).
    pub fn differences(&self, other: &MapParams) -> Vec<String> {
        let a = self.to_pairs();
        let b = other.to_pairs();
        a.iter()
            .zip(b.iter())
            .filter(|(x, y)| x.1 != y.1)
            .map(|(x, y)| format!("{}: {} vs {}", x.0, x.1, y.1))
            .collect()
    }

    /// Parameters as (name, value) text pairs, named like the CLI flags. Values print with
    /// Rust's shortest round-trip formatting, so parsing them back gives the same bits.
    pub fn to_pairs(&self) -> Vec<(&'static str, String)> {
        vec![
            ("resolution", self.resolution_m.to_string()),
            ("sf2", self.sf2.to_string()),
            ("ell", self.ell_m.to_string()),
            ("free_resolution", self.free_resolution_m.to_string()),
            ("ds_resolution", self.ds_resolution_m.to_string()),
            ("max_range", self.max_range_m.to_string()),
            ("range_mode", self.range_mode.as_str().to_string()),
            ("prior_a", self.prior_a.to_string()),
            ("prior_b", self.prior_b.to_string()),
            ("origin_as_free", self.origin_as_free.to_string()),
            ("sub_cells", self.sub_cells.to_string()),
            ("p_free", self.thresholds.p_free.to_string()),
            ("p_occ", self.thresholds.p_occ.to_string()),
            ("var_max", self.thresholds.var_max.to_string()),
        ]
    }

    /// Inverse of [`MapParams::to_pairs`]; every key must be present exactly once, except
    /// `sub_cells`, which maps written before it existed lack: they read as 0 (points where
    /// they are), which is what built them.
    pub fn from_pairs<'a>(pairs: impl IntoIterator<Item = (&'a str, &'a str)>) -> Result<Self, ParamError> {
        let mut p = MapParams { sub_cells: 0, ..MapParams::default() };
        let mut seen = std::collections::BTreeSet::from(["sub_cells".to_string()]);
        for (k, v) in pairs {
            let f = || {
                v.parse::<f64>().map_err(|_| ParamError::new(param_name(k), format!("not a number: {v:?}")))
            };
            match k {
                "resolution" => p.resolution_m = f()?,
                "sf2" => p.sf2 = f()?,
                "ell" => p.ell_m = f()?,
                "free_resolution" => p.free_resolution_m = f()?,
                "ds_resolution" => p.ds_resolution_m = f()?,
                "max_range" => p.max_range_m = f()?,
                "range_mode" => p.range_mode = v.parse()?,
                "prior_a" => p.prior_a = f()?,
                "prior_b" => p.prior_b = f()?,
                "origin_as_free" => {
                    p.origin_as_free =
                        v.parse().map_err(|_| ParamError::new("origin_as_free", "not a boolean"))?
                }
                "sub_cells" => {
                    p.sub_cells = v
                        .parse()
                        .map_err(|_| ParamError::new("sub_cells", format!("not a whole number: {v:?}")))?
                }
                "p_free" => p.thresholds.p_free = f()?,
                "p_occ" => p.thresholds.p_occ = f()?,
                "var_max" => p.thresholds.var_max = f()?,
                other => return Err(ParamError::new("parameters", format!("unknown parameter {other:?}"))),
            }
            seen.insert(k.to_string());
        }
        for (name, _) in MapParams::default().to_pairs() {
            if !seen.contains(name) {
                return Err(ParamError::new(name, "missing"));
            }
        }
        p.validate()?;
        Ok(p)
    }
}

fn param_name(k: &str) -> &'static str {
    MapParams::default().to_pairs().into_iter().map(|(n, _)| n).find(|n| *n == k).unwrap_or("parameters")
}

/// A parameter that is missing, malformed or out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid parameter {name}: {reason}")]
pub struct ParamError {
    pub name: &'static str,
    pub reason: String,
}

impl ParamError {
    pub fn new(name: &'static str, reason: impl fmt::Display) -> Self {
        Self { name, reason: reason.to_string() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_la3dm_head_and_valid() {
        let p = MapParams::default();
        p.validate().unwrap();
        assert_eq!((p.resolution_m, p.sf2, p.ell_m), (0.1, 1.0, 0.2));
        assert_eq!((p.free_resolution_m, p.ds_resolution_m), (0.5, 0.1));
        assert_eq!((p.prior_a, p.prior_b), (0.001, 0.001));
        assert_eq!(p.thresholds, Thresholds { p_free: 0.3, p_occ: 0.7, var_max: 100.0 });
    }

    #[test]
    fn pairs_round_trip_bit_exact() {
        let p = MapParams {
            ell_m: 0.3,
            sf2: 10.0,
            max_range_m: 7.3,
            range_mode: RangeMode::Drop,
            ..Default::default()
        };
        let pairs = p.to_pairs();
        let back = MapParams::from_pairs(pairs.iter().map(|(k, v)| (*k, v.as_str()))).unwrap();
        assert_eq!(back, p);
        assert!(p.differences(&back).is_empty());
        assert_eq!(p.differences(&MapParams::default()).len(), 4);
        let q = MapParams { sub_cells: 0, ..p };
        assert_eq!(p.differences(&q), ["sub_cells: 8 vs 0"]);
    }

    #[test]
    fn bad_parameters_name_the_field() {
        let bad = MapParams { ell_m: f64::NAN, ..Default::default() };
        assert_eq!(bad.validate().unwrap_err().name, "ell");
        let bad = MapParams { resolution_m: -0.1, ..Default::default() };
        assert_eq!(bad.validate().unwrap_err().name, "resolution");
        let bad = MapParams { ell_m: 5.0, ..Default::default() };
        assert_eq!(bad.validate().unwrap_err().name, "ell");
        let t = Thresholds { p_free: 0.8, p_occ: 0.7, var_max: 1.0 };
        assert_eq!(t.validate().unwrap_err().name, "p_free");
        for sub_cells in [3, 12, 128] {
            let bad = MapParams { sub_cells, ..Default::default() };
            assert_eq!(bad.validate().unwrap_err().name, "sub_cells", "{sub_cells}");
        }
        for sub_cells in [0, 1, 2, 64] {
            MapParams { sub_cells, ..Default::default() }.validate().unwrap();
        }
    }

    /// A map written before `sub_cells` existed has no such pair: it reads as 0, what built it.
    #[test]
    fn maps_without_sub_cells_read_as_points_where_they_are() {
        let p = MapParams::default();
        assert_eq!(p.sub_cells, 8);
        let pairs = p.to_pairs();
        let old: Vec<_> =
            pairs.iter().filter(|(k, _)| *k != "sub_cells").map(|(k, v)| (*k, v.as_str())).collect();
        assert_eq!(MapParams::from_pairs(old).unwrap(), MapParams { sub_cells: 0, ..p });
        let with = pairs.iter().map(|(k, v)| (*k, v.as_str()));
        assert_eq!(MapParams::from_pairs(with).unwrap(), p);
        let bad = pairs.iter().map(|(k, v)| (*k, if *k == "sub_cells" { "8.5" } else { v.as_str() }));
        assert_eq!(MapParams::from_pairs(bad).unwrap_err().name, "sub_cells");
    }
}
