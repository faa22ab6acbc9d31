//! ROC / AUC of an occupancy map against a ground-truth map (docs/algorithm.md §10).
//!
//! # Protocol
//!
//! The ground truth is a labelled set of cells (for the sample data: every 0.1 m
//! cell of the thresholded OctoMap `map.bt`, label `true` for occupied and `false`
//! for free; cells absent from the truth are not queried).
//!
//! - **Every truth cell is a query.** Its score is the map's predicted occupancy
//!   probability `p` at the cell centre.
//! - **A cell without evidence scores 0.5**, the "unknown" score. It still counts,
//!   so a map that covers less of the truth is penalised.
//! - **"Covered" cells** are the cells for which the map holds evidence. The
//!   "covered only" AUC restricts the queries to them. Always name the
//!   definition when reporting a covered-only number.
//!
//! This module does not know about maps: the caller builds the list of
//! `(score, label)` pairs (one per query cell, either for all truth cells or for
//! the covered ones) and hands it to [`roc`].
//!
//! # ROC and AUC
//!
//! The scores are sorted in descending order and ties are merged, giving one ROC
//! point per distinct score: sweeping the threshold down, each point is
//! `(FPR, TPR) = (FP / N, TP / P)` for "score ≥ threshold". The curve starts at
//! `(0, 0)` and ends at `(1, 1)`, and the AUC is the trapezoid rule along it.
//! Merging ties makes the trapezoid AUC equal to the Mann–Whitney statistic
//! `U / (P·N)` with ties counted one half: the probability that a random occupied
//! cell scores higher than a random free one.

use thiserror::Error;

/// Why a ROC curve could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum EvalError {
    /// No sample is labelled occupied, so the TPR is undefined.
    #[error("no positive (occupied) samples: the ROC curve is undefined")]
    NoPositives,
    /// No sample is labelled free, so the FPR is undefined.
    #[error("no negative (free) samples: the ROC curve is undefined")]
    NoNegatives,
    /// A score is NaN and cannot be ranked.
    #[error("score at index {index} is NaN")]
    NanScore {
        /// Index of the first NaN score in the input slice.
        index: usize,
    },
}

/// A ROC curve and its area.
#[derive(Debug, Clone, PartialEq)]
pub struct Roc {
    /// Area under the curve by the trapezoid rule, in `[0, 1]`.
    pub auc: f64,
    /// `(fpr, tpr)` points from `(0, 0)` to `(1, 1)`: the origin, then one point
    /// per distinct score in descending score order. Both coordinates are
    /// non-decreasing; the last point is exactly `(1.0, 1.0)`.
    pub points: Vec<(f64, f64)>,
    /// Number of samples labelled `true` (occupied), P.
    pub positives: usize,
    /// Number of samples labelled `false` (free), N.
    pub negatives: usize,
}

/// Computes the ROC curve and its trapezoid AUC.
///
/// `scores` holds `(predicted probability, label)` pairs with `label == true`
/// meaning occupied. The slice is reordered (sorted by descending score). Equal
/// scores are merged into one ROC point (`0.0` and `-0.0` are equal). Infinite
/// scores are ranked normally.
///
/// Runs in O(n log n). The AUC is accumulated in exact integer arithmetic and
/// divided once at the end, so it does not drift with the sample count.
///
/// # Errors
///
/// [`EvalError::NanScore`] if a score is NaN, [`EvalError::NoPositives`] or
/// [`EvalError::NoNegatives`] if one of the classes is empty (including an empty
/// input).
pub fn roc(scores: &mut [(f64, bool)]) -> Result<Roc, EvalError> {
    if let Some(index) = scores.iter().position(|(s, _)| s.is_nan()) {
        return Err(EvalError::NanScore { index });
    }
    let positives = scores.iter().filter(|(_, label)| *label).count();
    let negatives = scores.len() - positives;
    if positives == 0 {
        return Err(EvalError::NoPositives);
    }
    if negatives == 0 {
        return Err(EvalError::NoNegatives);
    }

    // Descending. total_cmp is a total order; with NaN excluded it only differs
    // from `==` in ordering -0.0 before 0.0, which are adjacent and merged below.
    scores.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));

    let p = positives as f64;
    let n = negatives as f64;
    let mut points = Vec::with_capacity(64);
    points.push((0.0, 0.0));

    // Twice the area in units of one (1/N × 1/P) cell: Σ Δfp · (tp_prev + tp).
    // Bounded by 2·P·N, which fits u128 for any slice length.
    let mut twice_area: u128 = 0;
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut rest: &[(f64, bool)] = scores;
    while let Some(&(score, _)) = rest.first() {
        let group_len = rest.iter().take_while(|(s, _)| *s == score).count();
        let (group, tail) = rest.split_at(group_len);
        let group_tp = group.iter().filter(|(_, label)| *label).count();
        let group_fp = group_len - group_tp;
        let tp_prev = tp;
        tp += group_tp;
        fp += group_fp;
        twice_area += group_fp as u128 * (tp_prev + tp) as u128;
        points.push((fp as f64 / n, tp as f64 / p));
        rest = tail;
    }

    let auc = twice_area as f64 / (2.0 * p * n);
    Ok(Roc { auc, points, positives, negatives })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Mann–Whitney U / (P·N), ties counted one half, computed naively in O(n²).
    fn naive_auc(scores: &[(f64, bool)]) -> f64 {
        let pos: Vec<f64> = scores.iter().filter(|s| s.1).map(|s| s.0).collect();
        let neg: Vec<f64> = scores.iter().filter(|s| !s.1).map(|s| s.0).collect();
        let mut u = 0.0;
        for &a in &pos {
            for &b in &neg {
                if a > b {
                    u += 1.0;
                } else if a == b {
                    u += 0.5;
                }
            }
        }
        u / (pos.len() as f64 * neg.len() as f64)
    }

    fn check_curve_shape(r: &Roc) {
        assert_eq!(r.points.first(), Some(&(0.0, 0.0)));
        assert_eq!(r.points.last(), Some(&(1.0, 1.0)));
        for w in r.points.windows(2) {
            assert!(w[1].0 >= w[0].0 && w[1].1 >= w[0].1, "not monotone: {w:?}");
            assert!(w[1] != w[0], "duplicate point: {w:?}");
        }
    }

    #[test]
    fn perfect_separation_is_one() {
        let mut s = vec![(0.9, true), (0.1, false), (0.8, true), (0.2, false), (0.3, false)];
        let r = roc(&mut s).expect("roc");
        assert_eq!(r.auc, 1.0);
        assert_eq!(r.positives, 2);
        assert_eq!(r.negatives, 3);
        assert_eq!(
            r.points,
            vec![(0.0, 0.0), (0.0, 0.5), (0.0, 1.0), (1.0 / 3.0, 1.0), (2.0 / 3.0, 1.0), (1.0, 1.0)]
        );
    }

    #[test]
    fn reversed_is_zero() {
        let mut s = vec![(0.1, true), (0.9, false), (0.2, true), (0.8, false)];
        let r = roc(&mut s).expect("roc");
        assert_eq!(r.auc, 0.0);
        check_curve_shape(&r);
    }

    #[test]
    fn all_ties_is_half() {
        let mut s = vec![(0.5, true), (0.5, false), (0.5, false), (0.5, true), (0.5, false)];
        let r = roc(&mut s).expect("roc");
        assert_eq!(r.auc, 0.5);
        assert_eq!(r.points, vec![(0.0, 0.0), (1.0, 1.0)]);
    }

    #[test]
    fn signed_zeros_are_one_tie() {
        let mut s = vec![(0.0, true), (-0.0, false)];
        let r = roc(&mut s).expect("roc");
        assert_eq!(r.auc, 0.5);
        assert_eq!(r.points.len(), 2);
    }

    #[test]
    fn hand_computed_example_with_ties() {
        // Scores (label): 0.9 (T), 0.7 (T), 0.7 (F), 0.5 (T), 0.5 (F), 0.5 (F), 0.2 (F).
        // P = 3, N = 4. ROC points, one per distinct score:
        //   start          (0,   0)
        //   0.9: tp 1 fp 0 (0,   1/3)
        //   0.7: tp 2 fp 1 (1/4, 2/3)
        //   0.5: tp 3 fp 3 (3/4, 1)
        //   0.2: tp 3 fp 4 (1,   1)
        // Trapezoids: 0 + 1/4·(1/3+2/3)/2 + 2/4·(2/3+1)/2 + 1/4·1
        //           = 1/8 + 5/12 + 1/4 = 19/24.
        // Mann–Whitney: pos 0.9 beats 4; pos 0.7 ties 1, beats 3 → 3.5;
        // pos 0.5 ties 2, beats 1 → 2. U = 9.5, U/(P·N) = 9.5/12 = 19/24.
        let mut s = vec![
            (0.5, false),
            (0.7, true),
            (0.2, false),
            (0.9, true),
            (0.5, true),
            (0.7, false),
            (0.5, false),
        ];
        let naive = naive_auc(&s);
        let r = roc(&mut s).expect("roc");
        assert!((r.auc - 19.0 / 24.0).abs() < 1e-15, "auc {}", r.auc);
        assert!((naive - 19.0 / 24.0).abs() < 1e-15, "naive {naive}");
        assert_eq!(r.positives, 3);
        assert_eq!(r.negatives, 4);
        assert_eq!(r.points, vec![(0.0, 0.0), (0.0, 1.0 / 3.0), (0.25, 2.0 / 3.0), (0.75, 1.0), (1.0, 1.0)]);
    }

    #[test]
    fn errors() {
        assert_eq!(roc(&mut []), Err(EvalError::NoPositives));
        assert_eq!(roc(&mut [(0.3, false)]), Err(EvalError::NoPositives));
        assert_eq!(roc(&mut [(0.3, true), (0.4, true)]), Err(EvalError::NoNegatives));
        assert_eq!(
            roc(&mut [(0.3, true), (f64::NAN, false), (f64::NAN, true)]),
            Err(EvalError::NanScore { index: 1 })
        );
    }

    #[test]
    fn infinite_scores_rank_normally() {
        let mut s = vec![(f64::INFINITY, true), (f64::NEG_INFINITY, false), (0.5, false)];
        let r = roc(&mut s).expect("roc");
        assert_eq!(r.auc, 1.0);
        check_curve_shape(&r);
    }

    #[test]
    fn large_input_with_ties() {
        // 2M samples with heavy ties (scores quantised to 1/1000); a
        // deterministic LCG keeps the test reproducible without extra deps.
        let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut next = || {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut s: Vec<(f64, bool)> = (0..2_000_000)
            .map(|_| {
                let label = next() < 0.07;
                let noise = next();
                let score = if label { 0.3 + 0.7 * noise } else { 0.7 * noise };
                ((score * 1000.0).round() / 1000.0, label)
            })
            .collect();
        // An accidental O(n²) would not finish here.
        let r = roc(&mut s).expect("roc");
        check_curve_shape(&r);
        assert!(r.points.len() <= 1002);
        // Uniform overlap on [0.3, 0.7]: AUC = 1 − (4/7)²/2 ≈ 0.8367.
        assert!((r.auc - (1.0 - 0.5 * (4.0f64 / 7.0).powi(2))).abs() < 5e-3, "auc {}", r.auc);
    }

    proptest! {
        #[test]
        fn matches_naive_mann_whitney(
            samples in proptest::collection::vec(
                (prop_oneof![
                    // few distinct values → many ties
                    (0u8..6).prop_map(|k| f64::from(k) / 5.0),
                    0.0f64..1.0,
                ], any::<bool>()),
                2..60,
            )
        ) {
            let has_pos = samples.iter().any(|s| s.1);
            let has_neg = samples.iter().any(|s| !s.1);
            prop_assume!(has_pos && has_neg);
            let naive = naive_auc(&samples);
            let mut s = samples.clone();
            let r = roc(&mut s).expect("roc");
            prop_assert!((r.auc - naive).abs() < 1e-12, "roc {} naive {}", r.auc, naive);
            check_curve_shape(&r);
            let mut distinct: Vec<f64> = samples.iter().map(|s| s.0).collect();
            distinct.sort_by(f64::total_cmp);
            distinct.dedup();
            prop_assert_eq!(r.points.len(), distinct.len() + 1);
        }
    }
}
