//! The posterior of one cell: its evidence, two fixed-point kernel sums, and the Beta
//! posterior derived from them (docs/algorithm.md Eq. 1, 2, 7 and 9).
//!
//! A cell stores only `A = Σ_hits q` and `B = Σ_free q` (unit kernel, fixed point). Everything a
//! reader wants — probability, variance, log-odds, state — is derived on demand from
//! `α = α0 + σ0·A/2^F`, `β = β0 + σ0·B/2^F`. Cells that never received evidence (both sums
//! zero) answer with the prior (p = 0.5). The sums are integers with [`FIXED_SHIFT`] fractional
//! bits, so any scan order, thread count or merge order gives identical bits; that unit is a
//! fact of the model, which the kernel's quantisation imports.
//!
//! Depends on `params` only.

use super::params::{MapParams, Thresholds};

/// Fractional bits of the fixed-point evidence sums (docs/algorithm.md §7).
pub const FIXED_SHIFT: u32 = 24;
/// `2^FIXED_SHIFT` as f64: one unit of kernel mass.
pub const FIXED_ONE: f64 = (1u64 << FIXED_SHIFT) as f64;

/// The raw evidence of one cell: occupied mass `a` and free mass `b` (fixed-point, unit kernel).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[repr(C)]
pub struct Evidence {
    pub a: i64,
    pub b: i64,
}

impl Evidence {
    pub fn is_empty(self) -> bool {
        self.a == 0 && self.b == 0
    }
}

/// Free / occupied / unknown under a set of thresholds (Eq. 9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum CellState {
    Free,
    Occupied,
    Unknown,
}

impl CellState {
    pub fn as_str(self) -> &'static str {
        match self {
            CellState::Free => "free",
            CellState::Occupied => "occupied",
            CellState::Unknown => "unknown",
        }
    }
}

/// What a reader gets for one cell. `repr(C)`: see [`super::query::PointAnswer`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub struct CellEstimate {
    pub probability: f64,
    pub variance: f64,
    pub state: CellState,
    pub evidence: Evidence,
}

impl CellEstimate {
    /// Eq. 1, 2 and 9 from the stored sums.
    pub fn from_evidence(e: Evidence, params: &MapParams, th: &Thresholds) -> Self {
        Self::from_moments(e, probability_variance(e, params), th)
    }

    /// The estimate of evidence `e` whose [`probability_variance`] is `(probability, variance)`.
    #[inline(always)]
    pub(crate) fn from_moments(e: Evidence, (probability, variance): (f64, f64), th: &Thresholds) -> Self {
        let state = if probability < th.p_free && variance < th.var_max {
            CellState::Free
        } else if probability > th.p_occ && variance < th.var_max {
            CellState::Occupied
        } else {
            CellState::Unknown
        };
        Self { probability, variance, state, evidence: e }
    }

    /// The Beta posterior's parameters `(α, β)`: prior plus kernel-weighted hit / free mass.
    pub fn alpha_beta(&self, params: &MapParams) -> (f64, f64) {
        alpha_beta(self.evidence, params)
    }

    /// Eq. 7: `log(α/β)`.
    pub fn log_odds(&self, params: &MapParams) -> f64 {
        let (alpha, beta) = alpha_beta(self.evidence, params);
        (alpha / beta).ln()
    }
}

/// Eq. 1 and 2: the Beta posterior's mean and variance (the one place they are computed, so a
/// block summary and a cell estimate agree to the bit).
#[inline]
pub(crate) fn probability_variance(e: Evidence, params: &MapParams) -> (f64, f64) {
    let (alpha, beta) = alpha_beta(e, params);
    mean_variance(alpha, beta)
}

/// The mean and variance of Beta(`alpha`, `beta`).
#[inline(always)]
pub(crate) fn mean_variance(alpha: f64, beta: f64) -> (f64, f64) {
    let w = alpha + beta;
    (alpha / w, alpha * beta / (w * w * (w + 1.0)))
}

#[inline(always)]
pub(crate) fn alpha_beta(e: Evidence, params: &MapParams) -> (f64, f64) {
    (
        params.prior_a + params.sf2 * (e.a as f64 / FIXED_ONE),
        params.prior_b + params.sf2 * (e.b as f64 / FIXED_ONE),
    )
}
