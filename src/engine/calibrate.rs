//! Calibration at load: the search a model serves, chosen on the CPU it runs on. A search's
//! agreement with the exhaustive argmax is the model's (the bundle's search study measured it,
//! [`SearchStudy`]); its latency is the CPU's. The calibration times what a search is made of on
//! this CPU — the encoder, a start level in full, and rows of the head in each precision (min of
//! a few runs each) — predicts each studied search's latency from the rows it scores (a fixed
//! number per level), and picks, among the searches whose agreement reaches the target, the most
//! agreeing one predicted within the budget (ties: the fastest); when none fits, the fastest of
//! them, flagged as over budget. It never picks a search below the target. Without a study it
//! keeps the configured search's shape and only chooses its coarse precision among f32, bfloat16
//! and f16 (which rank cells like f32, up to rounding, so each twin is taken to agree as well;
//! not 8-bit integers, whose scores are a few % off: they are served only where a study
//! measured them). A search in a precision this CPU only emulates is left out where the same
//! search in f32 is a candidate (it would score the same rows, slower). The chosen search is
//! then run for real and its latency reported beside the prediction.

use std::collections::BTreeMap;
use std::time::Instant;

use super::search::Keep;
use super::{EngineError, Model, PredictOptions, SearchParams};
use crate::bundle::study::SearchStudy;
use crate::net::Precision;

/// The default latency budget of a search (the server's `--search-budget-ms`), in milliseconds.
pub const DEFAULT_SEARCH_BUDGET_MS: f64 = 25.0;

/// Timed runs of each measurement (the minimum is kept).
const RUNS: usize = 2;

/// Rows of the head timed per precision, many and few (a level's fixed cost).
const TIMED_ROWS: usize = 2048;
const SMALL_ROWS: usize = 64;

/// Predictions within this factor of the fastest count as equally fast.
const TIE: f64 = 1.15;

/// Top-k of the searches the calibration times (the bench's and a typical Predict's).
const TOP_K: usize = 10;

/// What a calibration chose, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The search chosen.
    pub chosen: SearchParams,
    /// Its agreement in the bundle's study (`None` without a study).
    pub agreement: Option<f64>,
    /// Its predicted latency (encoder included), in milliseconds.
    pub predicted_ms: f64,
    /// Its latency measured once chosen (median of three runs), in milliseconds.
    pub measured_ms: f64,
    /// The latency budget.
    pub budget_ms: f64,
    /// Whether the prediction is within the budget.
    pub within_budget: bool,
    /// Searches that reached the agreement target (those the calibration chose among).
    pub eligible: usize,
    /// How long the calibration took, in milliseconds.
    pub took_ms: f64,
    /// Why this search, in words.
    pub reason: String,
}

/// The measured costs a prediction is made of, in milliseconds.
struct Rates {
    encoder: f64,
    /// Per start level and precision: scoring the level in full from its projections.
    start: BTreeMap<(u8, Precision), f64>,
    /// Per precision: a level's fixed cost and one row's, from encodings (a line through the
    /// times of [`SMALL_ROWS`] and [`TIMED_ROWS`] rows).
    row: BTreeMap<Precision, (f64, f64)>,
}

impl Rates {
    /// The predicted latency of `search` to `level`.
    fn predict(&self, model: &Model, search: &SearchParams, level: u8) -> f64 {
        let mut ms = self.encoder;
        for (l, rows, precision) in rows_per_level(model, search, level) {
            ms += if l == search.start_level.min(level) {
                self.start[&(l, precision)]
            } else {
                let (fixed, per_row) = self.row[&precision];
                fixed + rows as f64 * per_row
            };
        }
        ms
    }
}

/// The levels `search` scores to `level` with a top-[`TOP_K`], each with the rows it scores (at
/// most: a keep by mass may keep fewer) and its precision.
pub fn rows_per_level(
    model: &Model,
    search: &SearchParams,
    level: u8,
) -> Vec<(u8, usize, Precision)> {
    let start = search.start_level.min(level);
    let precision = |l: u8| {
        if l == level {
            Precision::F32
        } else {
            search.coarse_precision
        }
    };
    let min = TOP_K.div_ceil(8);
    let keep = Keep {
        max: search.keep.max(min),
        min,
        mass: search.keep_mass,
        taper: search.keep_taper,
    };
    let mut out = Vec::new();
    let mut cells = model.grid(start).map_or(0, |g| g.len());
    out.push((start, cells, precision(start)));
    for l in start + 1..=level {
        let kept = keep.max_at((l - start - 1) as usize).min(cells);
        cells = 8 * kept;
        out.push((l, cells, precision(l)));
    }
    out
}

/// Median of `runs` timed calls of `f`, in milliseconds (after one untimed call), or the minimum
/// with `min`.
fn time_ms(runs: usize, min: bool, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    if min { t[0] } else { t[t.len() / 2] }
}

/// A search the calibration may choose, with its studied agreement.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    params: SearchParams,
    agreement: Option<f64>,
}

/// The searches to choose among: the study's that reach `target` (within this model's levels),
/// or, without a study, `configured` in both precisions.
fn candidates(
    model: &Model,
    study: Option<&SearchStudy>,
    configured: &SearchParams,
    target: f64,
) -> Vec<Candidate> {
    match study {
        Some(study) => study
            .searches
            .iter()
            .filter(|s| s.agreement >= target && s.start_level <= model.config.max_full_level)
            .filter_map(|s| {
                Some(Candidate {
                    params: SearchParams {
                        start_level: s.start_level,
                        keep: s.keep,
                        keep_mass: s.keep_mass,
                        keep_taper: s.keep_taper,
                        coarse_precision: s.precision().ok()?,
                    },
                    agreement: Some(s.agreement),
                })
            })
            .collect(),
        // Not i8: its scores are a few % from f32's, so a search in it is served only where a
        // study measured its agreement.
        None => [Precision::F32, Precision::Bf16, Precision::F16]
            .map(|coarse_precision| Candidate {
                params: SearchParams {
                    coarse_precision,
                    ..*configured
                },
                agreement: None,
            })
            .to_vec(),
    }
}

/// The candidates less those whose coarse precision is emulated on this CPU (the f32 GEMM with
/// the precision's rounding, never faster than f32) while their f32 twin, the same search in
/// f32, is a candidate too: the twin scores the same rows at least as fast and reaches the
/// target as well, so the emulation is neither timed nor chosen. An emulated search without an
/// f32 twin stays (it may score fewer rows than any f32 candidate).
fn without_emulated_twins(
    candidates: Vec<Candidate>,
    native: impl Fn(Precision) -> bool,
) -> Vec<Candidate> {
    let has_f32_twin = |c: &Candidate| {
        let twin = SearchParams {
            coarse_precision: Precision::F32,
            ..c.params
        };
        candidates.iter().any(|other| other.params == twin)
    };
    let kept: Vec<bool> = candidates
        .iter()
        .map(|c| native(c.params.coarse_precision) || !has_f32_twin(c))
        .collect();
    candidates
        .into_iter()
        .zip(kept)
        .filter_map(|(c, keep)| keep.then_some(c))
        .collect()
}

/// Chooses the search `model` serves to `level` on this CPU (see the module's doc).
pub fn calibrate(
    model: &Model,
    study: Option<&SearchStudy>,
    configured: &SearchParams,
    target: f64,
    budget_ms: f64,
    level: u8,
) -> Result<Calibration, EngineError> {
    let started = Instant::now();
    let candidates = without_emulated_twins(candidates(model, study, configured, target), |p| {
        model.fused.native(p)
    });
    if candidates.is_empty() {
        return Err(EngineError::InvalidArgument {
            field: "search study".into(),
            message: format!(
                "no studied search of this model reaches the agreement target {target} (lower --search-agreement or set the search with flags)"
            ),
        });
    }
    let size = model.input_size() as usize;
    let grey = vec![128u8; size * size * 3];
    let rates = measure_rates(model, &candidates, &grey, level)?;
    let predicted: Vec<f64> = candidates
        .iter()
        .map(|c| rates.predict(model, &c.params, level))
        .collect();
    let rows: Vec<usize> = candidates
        .iter()
        .map(|c| {
            rows_per_level(model, &c.params, level)
                .iter()
                .map(|r| r.1)
                .sum()
        })
        .collect();
    let agreement: Vec<f64> = candidates
        .iter()
        .map(|c| c.agreement.unwrap_or(0.0))
        .collect();
    let (pick, reason) = choose(&rows, &agreement, &predicted, budget_ms);
    let chosen = candidates[pick];
    let options = PredictOptions {
        top_k: TOP_K,
        level: Some(level),
        mode_angle_deg: None,
        ..Default::default()
    };
    let mut failed = None;
    let measured_ms = time_ms(3, false, || {
        let searched = model
            .features(&[&grey])
            .and_then(|f| model.predict_searching(&f, &options, &chosen.params, &[None]));
        if let Err(e) = searched {
            failed = Some(e);
        }
    });
    if let Some(e) = failed {
        return Err(e);
    }
    Ok(Calibration {
        chosen: chosen.params,
        agreement: chosen.agreement,
        predicted_ms: predicted[pick],
        measured_ms,
        budget_ms,
        within_budget: predicted[pick] <= budget_ms,
        eligible: candidates.len(),
        took_ms: started.elapsed().as_secs_f64() * 1e3,
        reason: match study {
            Some(_) => reason,
            None => format!("no search study in the bundle: the configured search, {reason}"),
        },
    })
}

/// The encoder's time and the head's rates on this CPU, for every start level and precision
/// the `candidates` use, measured on the `grey` image.
fn measure_rates(
    model: &Model,
    candidates: &[Candidate],
    grey: &[u8],
    level: u8,
) -> Result<Rates, EngineError> {
    let features = model.features(&[grey])?;
    let mut rates = Rates {
        encoder: time_ms(RUNS, true, || {
            let _ = model.features(&[grey]);
        }),
        start: BTreeMap::new(),
        row: BTreeMap::new(),
    };
    let grid = model
        .grid(level)
        .ok_or_else(|| EngineError::InvalidArgument {
            field: "level".into(),
            message: format!("{level} is above this model's grids"),
        })?;
    let step = (grid.len() / TIMED_ROWS).max(1) as u64;
    let rotations: Vec<[f32; 9]> = (0..TIMED_ROWS as u64)
        .map(|i| crate::so3::to_row_major_f32(&grid.rotation((i * step) % grid.len() as u64)))
        .collect();
    for c in candidates {
        for (l, _, precision) in rows_per_level(model, &c.params, level) {
            if l == c.params.start_level.min(level) {
                rates.start.entry((l, precision)).or_insert_with(|| {
                    time_ms(RUNS, true, || {
                        let _ =
                            model.projected[l as usize].log_weights_of_row(precision, &features[0]);
                    })
                });
            } else {
                rates.row.entry(precision).or_insert_with(|| {
                    let time = |rows: &[[f32; 9]]| {
                        let rows = [rows.to_vec()];
                        time_ms(RUNS, true, || {
                            let _ = model.score_rotations_many(&features, &rows, precision);
                        })
                    };
                    let (many, few) = (time(&rotations), time(&rotations[..SMALL_ROWS]));
                    let per_row = ((many - few) / (TIMED_ROWS - SMALL_ROWS) as f64).max(0.0);
                    ((few - per_row * SMALL_ROWS as f64).max(0.0), per_row)
                });
            }
        }
    }
    Ok(rates)
}

/// The candidate to serve and why: the most agreeing one predicted within `budget_ms`, else the
/// fastest. Timings are noisy: searches predicted within [`TIE`] of the fastest of a set count as
/// equally fast, and the one scoring the fewest rows is taken, so that the choice does not flip
/// between starts; among those the lower prediction (twins in other precisions score the same
/// rows), then the study's order.
fn choose(rows: &[usize], agreement: &[f64], predicted: &[f64], budget_ms: f64) -> (usize, String) {
    let fastest = |set: &[usize]| -> Option<usize> {
        let best = set
            .iter()
            .map(|&i| predicted[i])
            .fold(f64::INFINITY, f64::min);
        set.iter()
            .copied()
            .filter(|&i| predicted[i] <= best * TIE)
            .min_by(|&a, &b| {
                (rows[a].cmp(&rows[b]))
                    .then(predicted[a].total_cmp(&predicted[b]))
                    .then(a.cmp(&b))
            })
    };
    let within: Vec<usize> = (0..predicted.len())
        .filter(|&i| predicted[i] <= budget_ms)
        .collect();
    let most = within
        .iter()
        .map(|&i| agreement[i])
        .fold(f64::NEG_INFINITY, f64::max);
    let most_agreeing: Vec<usize> = within
        .iter()
        .copied()
        .filter(|&i| agreement[i] >= most)
        .collect();
    let all: Vec<usize> = (0..predicted.len()).collect();
    match fastest(&most_agreeing) {
        Some(i) => (
            i,
            format!(
                "the most agreeing of {} searches predicted within {budget_ms} ms",
                within.len()
            ),
        ),
        None => (
            fastest(&all).unwrap_or(0),
            format!(
                "no search reaching the target is predicted within {budget_ms} ms: the fastest of {}",
                predicted.len()
            ),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::{Candidate, choose, without_emulated_twins};
    use crate::engine::SearchParams;
    use crate::net::Precision;

    fn search(start_level: u8, keep: usize, coarse_precision: Precision) -> Candidate {
        Candidate {
            params: SearchParams {
                start_level,
                keep,
                keep_mass: None,
                keep_taper: 0.5,
                coarse_precision,
            },
            agreement: Some(1.0),
        }
    }

    #[test]
    fn emulated_searches_with_an_f32_twin_are_left_out() {
        let candidates = vec![
            search(2, 512, Precision::F32),
            search(2, 512, Precision::Bf16),
            search(2, 512, Precision::I8),
            search(1, 512, Precision::I8),
            search(1, 512, Precision::F16),
        ];
        // bfloat16 and f16 emulated, i8 native: the bf16 twin of an f32 search goes; the f16
        // search without an f32 twin stays, as do the native ones.
        let native = |p: Precision| matches!(p, Precision::F32 | Precision::I8);
        let kept: Vec<_> = without_emulated_twins(candidates.clone(), native)
            .iter()
            .map(|c| (c.params.start_level, c.params.coarse_precision))
            .collect();
        assert_eq!(
            kept,
            [
                (2, Precision::F32),
                (2, Precision::I8),
                (1, Precision::I8),
                (1, Precision::F16)
            ]
        );
        // Everything native: nothing leaves.
        assert_eq!(without_emulated_twins(candidates, |_| true).len(), 5);
    }

    #[test]
    fn twins_scoring_the_same_rows_go_to_the_faster_one_even_within_the_tie() {
        // An f16 search and its i8 twin (same rows), the twin 10 % faster: within TIE, and
        // the study lists f16 first.
        let (pick, _) = choose(&[1000, 1000], &[1.0, 1.0], &[20.0, 18.0], 25.0);
        assert_eq!(pick, 1);
    }

    #[test]
    fn within_the_tie_fewer_rows_win_over_a_faster_prediction() {
        let (pick, _) = choose(&[1000, 800], &[1.0, 1.0], &[18.0, 20.0], 25.0);
        assert_eq!(pick, 1);
        // Out of the tie the faster one wins.
        let (pick, _) = choose(&[1000, 800], &[1.0, 1.0], &[15.0, 20.0], 25.0);
        assert_eq!(pick, 0);
    }

    #[test]
    fn agreement_first_within_the_budget_else_the_fastest() {
        let (pick, reason) = choose(&[1000, 500], &[1.0, 0.99], &[20.0, 10.0], 25.0);
        assert_eq!(pick, 0, "{reason}");
        let (pick, reason) = choose(&[1000, 500], &[1.0, 0.99], &[40.0, 30.0], 25.0);
        assert_eq!(pick, 1, "{reason}");
        assert!(reason.contains("no search"), "{reason}");
    }
}
