//! Calibration at load: the search a model serves, chosen on the CPU it runs on. A search's
//! agreement with the exhaustive argmax is the model's (the bundle's search study measured it,
//! [`SearchStudy`]); its latency is the CPU's. The calibration times what a search is made of on
//! this CPU — the encoder, and rows of the head in each precision, by both branches or by the shape
//! branch alone, gathered from a full level's projections or (above the full levels) encoded from
//! their rotations (each the minimum of two runs) — predicts each studied search's latency from the
//! rows it scores (a fixed number per level; a start level scored in full is a level of projected
//! rows like the others, predicted from the same line, not timed on its own), and picks, among the
//! searches whose agreement reaches the target, the most agreeing one predicted within the budget
//! (agreements one studied image apart count as equal, [`TIE_IMAGES`]; ties: the fastest); when
//! none fits, the fastest of them, flagged as over budget. A search predicted just over the budget
//! that would be chosen within it is timed again before it is ruled out (`estimate_and_retime`). It
//! never picks a search below the target. Without a study it keeps the configured search's shape
//! and only chooses its coarse precision among f32, bfloat16 and f16 (which rank cells like f32, up
//! to rounding, so each twin is taken to agree as well; not 8-bit integers, whose scores are a
//! few % off: they are served only where a study measured them). A search in a precision this CPU
//! only emulates is left out where the same search in f32 is a candidate (it would score the same
//! rows, slower). Measurements are made on demand, for the search with the lowest latency bound
//! among those that may still be chosen: a cost not measured yet bounds the prediction from below
//! (as 0, or as f32's where the precision is emulated), and a search whose bound already loses is
//! never timed in full. Past a deadline ([`MEASURING_DEADLINE_MS`]) it measures only until one
//! search's prediction is exact. The chosen search is then run once for real and its latency
//! reported beside the prediction.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use super::search::Keep;
use super::{EngineError, Model, PredictOptions, RESCORED_CELLS, SearchParams};
use crate::bundle::study::SearchStudy;
use crate::net::{Branches, Precision};

/// The default latency budget of a search (the server's `--search-budget-ms`), in milliseconds.
pub const DEFAULT_SEARCH_BUDGET_MS: f64 = 25.0;

/// Timed runs of each measurement (the minimum is kept).
const RUNS: usize = 2;

/// Timed runs of a measurement made again (see [`estimate_and_retime`]).
const RETIMED_RUNS: usize = 3;

/// A search predicted over the budget by at most this factor is timed again before it is ruled
/// out, if it would be chosen within the budget ([`estimate_and_retime`]).
const RETIME_BEYOND: f64 = 1.5;

/// Rows of the head timed per precision, many and few (a level's fixed cost), each the minimum
/// of [`RUNS`]: 2 048 rows timed once left one slow timing uncorrected, and the choice flipped
/// with it (docs/BENCHMARKS.md, 2026-12-01). 512 rows are four tiles of 128 rows (two a core) on
/// a 512 KiB L2 and two of 256 on larger ones: every core busy, as in a search's levels, at half
/// the cost of 1 024 (docs/BENCHMARKS.md, 2026-12-07).
const TIMED_ROWS: usize = 512;
const SMALL_ROWS: usize = 64;

/// After this long, a calibration measures only until one search's prediction is exact
/// ([`calibrate_within`]); it took 45–100 ms a model on a 2-core AMD EPYC with AVX-512 and
/// 73–203 ms on 2-core Intel Xeons with AMX while the start levels were timed in full, and
/// 127–202 ms on a 2-core AMD Zen 3 (AVX2 only) once they were predicted from the rows and each
/// part was timed again at most once (30 calibrations), 84–160 ms there with 512 rows timed
/// instead of 1 024 (70 calibrations, docs/BENCHMARKS.md, 2026-12-07).
pub const MEASURING_DEADLINE_MS: f64 = 250.0;

/// Predictions within this factor of the fastest count as equally fast. A search and its twin
/// that rescores the finest level from 8-bit scores are predicted 1.08–1.17 apart on a 2-core
/// Intel Xeon with AMX, so a tie at 1.15 let timing noise choose between them (the same choice in
/// 75–90 % of 40 calibrations; in 97.5–100 % at 1.25 with [`TIMED_ROWS`] timed twice,
/// docs/BENCHMARKS.md).
const TIE: f64 = 1.25;

/// Agreements this many studied images apart count as equal: at 99 % over a 100-image study,
/// one image is about the binomial standard error, so ranking on it would let timing noise
/// decide between searches that agree equally well (a search predicted near the budget flips in
/// and out of it between starts, and with it the choice).
const TIE_IMAGES: f64 = 1.0;

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
    /// Its latency measured once chosen (one run, after the rates warmed its parts), in
    /// milliseconds.
    pub measured_ms: f64,
    /// The latency budget.
    pub budget_ms: f64,
    /// Whether the prediction is within the budget.
    pub within_budget: bool,
    /// Searches that reached the agreement target (those the calibration chose among).
    pub eligible: usize,
    /// How long the calibration took, in milliseconds.
    pub took_ms: f64,
    /// Where that time went.
    pub spent: Spent,
    /// Why this search, in words.
    pub reason: String,
}

/// Where a calibration's time went, in milliseconds: timing the encoder, the head's rows, and
/// running the chosen search (`check`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Spent {
    /// Timing the encoder.
    pub encoder_ms: f64,
    /// Timing the head's rows, in each precision (a start level in full is predicted from them).
    pub rows_ms: f64,
    /// Running the chosen search.
    pub check_ms: f64,
    /// Measurements made of the head's rows (the encoder's and the check's not counted).
    pub measurements: usize,
    /// Searches predicted just over the budget whose measurements were made again.
    pub retimed: usize,
}

impl std::fmt::Display for Spent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "encoder {:.0} ms, {} measurements of head rows {:.0} ms ({} searches timed again), the chosen search {:.0} ms",
            self.encoder_ms, self.measurements, self.rows_ms, self.retimed, self.check_ms
        )
    }
}

impl std::fmt::Display for Calibration {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let agreement = self
            .agreement
            .map_or("not studied".into(), |a| format!("{a:.3}"));
        write!(
            f,
            "({:.0} ms: {}): {} — agreement {agreement}, predicted {:.1} ms, measured {:.1} ms, budget {} ms; {}",
            self.took_ms,
            self.spent,
            self.chosen,
            self.predicted_ms,
            self.measured_ms,
            self.budget_ms,
            self.reason
        )
    }
}

/// The arithmetic of a level's rows: its precision, and the branches that score them.
type Arithmetic = (Precision, Branches);

/// Where a refined level's rows come from: a full level's precomputed projections, gathered,
/// or (above the full levels) the cells' rotations, encoded and projected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Source {
    Projected,
    Encoded,
}

/// A measurement a prediction needs: the head's rows from a source, in an arithmetic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Need(Source, Arithmetic);

/// The costs measured so far, in milliseconds.
struct Rates {
    encoder: f64,
    /// Per measurement: the times of [`SMALL_ROWS`] and of [`TIMED_ROWS`] rows (a line through
    /// them gives a level's fixed cost and one row's, [`line`]).
    row: BTreeMap<Need, (f64, f64)>,
}

/// A level's fixed cost and one row's, from the times of [`SMALL_ROWS`] (`few`) and
/// [`TIMED_ROWS`] (`many`) rows.
fn line((few, many): (f64, f64)) -> (f64, f64) {
    let per_row = ((many - few) / (TIMED_ROWS - SMALL_ROWS) as f64).max(0.0);
    let fixed = (few - per_row * SMALL_ROWS as f64).max(0.0);
    (fixed, per_row)
}

impl Rates {
    /// The predicted latency of `search` to `level`, exact when every cost it is made of was
    /// measured (the `Need` is `None`). Otherwise a lower bound, with the first measurement
    /// missing: a cost not measured counts as its f32 counterpart's where the precision is
    /// `emulated` (the f32 GEMM and a rounding, never faster than f32) and that was measured,
    /// else as 0.
    fn predict(
        &self,
        model: &Model,
        search: &SearchParams,
        level: u8,
        emulated: impl Fn(Precision) -> bool,
    ) -> (f64, Option<Need>) {
        let mut ms = self.encoder;
        let mut missing = None;
        for (l, rows, precision, branches) in rows_per_level(model, search, level) {
            let need = |p: Precision| part(model, l, (p, branches));
            let cost = |p: Precision| self.cost(need(p), rows);
            match cost(precision) {
                Some(c) => ms += c,
                None => {
                    let twin = emulated(precision).then(|| cost(Precision::F32));
                    ms += twin.flatten().unwrap_or(0.0);
                    missing = missing.or(Some(match twin {
                        Some(None) => need(Precision::F32),
                        _ => need(precision),
                    }));
                }
            }
        }
        (ms, missing)
    }

    /// What `rows` rows of `need` cost, when it was measured.
    fn cost(&self, need: Need, rows: usize) -> Option<f64> {
        self.row.get(&need).map(|&timed| {
            let (fixed, per_row) = line(timed);
            fixed + rows as f64 * per_row
        })
    }
}

/// The measurement that level `l` needs in `arithmetic`: rows from a full level's projections
/// (the start level scored in full among them: the same kernels on a longer block of rows), or
/// (above the full levels) from rotations.
fn part(model: &Model, l: u8, arithmetic: Arithmetic) -> Need {
    if (l as usize) < model.projected.len() {
        Need(Source::Projected, arithmetic)
    } else {
        Need(Source::Encoded, arithmetic)
    }
}

/// Every measurement `search` to `level` is predicted from.
fn parts(model: &Model, search: &SearchParams, level: u8) -> Vec<Need> {
    let mut needs: Vec<Need> = rows_per_level(model, search, level)
        .into_iter()
        .map(|(l, _, precision, branches)| part(model, l, (precision, branches)))
        .collect();
    needs.sort();
    needs.dedup();
    needs
}

/// The levels `search` scores to `level` with a top-[`TOP_K`], each with the rows it scores (at
/// most: a keep by mass may keep fewer), their precision and the branches that score them; a
/// search that rescores the finest level lists it twice, the second time with the rows
/// rescored in f32.
pub fn rows_per_level(
    model: &Model,
    search: &SearchParams,
    level: u8,
) -> Vec<(u8, usize, Precision, Branches)> {
    let start = search.start_level.min(level);
    let precision = |l: u8| search.precision_at(l, start, level);
    let branches = |l: u8| search.branches_at(l, level);
    let min = TOP_K.div_ceil(8);
    let keep = Keep {
        max: search.keep.max(min),
        min,
        mass: search.keep_mass,
        taper: search.keep_taper,
    };
    let mut out = Vec::new();
    let mut cells = model.grid(start).map_or(0, |g| g.len());
    out.push((start, cells, precision(start), branches(start)));
    for l in start + 1..=level {
        let kept = keep.max_at((l - start - 1) as usize).min(cells);
        cells = 8 * kept;
        out.push((l, cells, precision(l), branches(l)));
    }
    if search.rescores_to(start, level) {
        let rescored = RESCORED_CELLS.max(TOP_K).min(cells);
        out.push((level, rescored, Precision::F32, Branches::Both));
    }
    out
}

/// The minimum of `runs` timed calls of `f`, in milliseconds. No untimed call comes first: a
/// minimum leaves a cold first call out (and [`Meter`] times the few rows before the many).
fn min_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs.max(1))
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

/// The candidates' studied agreements (0 without a study), and how far apart two may be and still
/// count as equal ([`TIE_IMAGES`] over the study's images).
struct Agreement {
    of: Vec<f64>,
    tie: f64,
}

impl Agreement {
    /// The highest agreement among `set` (−∞ for none).
    fn most(&self, set: &[usize]) -> f64 {
        set.iter()
            .map(|&i| self.of[i])
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Whether candidate `i` agrees as well as `most`, within the tie.
    fn ties(&self, i: usize, most: f64) -> bool {
        self.of[i] >= most - self.tie - 1e-12
    }
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
                    params: SearchParams::of_studied(s)?,
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
            rescore_finest: false,
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
    calibrate_within(
        model,
        study,
        configured,
        target,
        budget_ms,
        level,
        MEASURING_DEADLINE_MS,
    )
}

/// [`calibrate`] with another deadline for its measurements: once `deadline_ms` have passed, it
/// measures only until one search's prediction is exact, and chooses among the exact ones (a
/// slow or busy CPU still loads its models in bounded time, never below the target).
pub fn calibrate_within(
    model: &Model,
    study: Option<&SearchStudy>,
    configured: &SearchParams,
    target: f64,
    budget_ms: f64,
    level: u8,
    deadline_ms: f64,
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
    // The branch-rows each scores: a row the shape branch alone scores counts half of one
    // both branches score.
    let rows: Vec<usize> = candidates
        .iter()
        .map(|c| {
            rows_per_level(model, &c.params, level)
                .iter()
                .map(|r| r.1 * r.3.count())
                .sum()
        })
        .collect();
    let agreement = Agreement {
        of: candidates
            .iter()
            .map(|c| c.agreement.unwrap_or(0.0))
            .collect(),
        tie: study.map_or(0.0, |s| TIE_IMAGES / s.images.max(1) as f64),
    };
    let mut meter = Meter::new(model, &grey, level)?;
    let (estimates, cut_short) = estimate_and_retime(
        &mut meter,
        (&candidates, &rows, &agreement),
        (level, budget_ms),
        (started, deadline_ms),
    );
    let mut spent = meter.spent;
    // A search left with a bound cannot be chosen (see `next_need`), or was not measured in time.
    let ruled_out = estimates.iter().filter(|e| e.1.is_some()).count();
    let left_out = if cut_short {
        format!(
            "measuring stopped at the {deadline_ms} ms deadline: {ruled_out} searches not timed in full"
        )
    } else {
        format!("{ruled_out} more ruled out by a lower bound on their latency, not timed in full")
    };
    let predicted = exact_predictions(&estimates);
    let (pick, reason) = choose(&rows, &agreement, &predicted, budget_ms);
    let chosen = candidates[pick];
    let measured_ms = run_once(model, &grey, &chosen.params, level)?;
    spent.check_ms = measured_ms;
    Ok(Calibration {
        chosen: chosen.params,
        agreement: chosen.agreement,
        predicted_ms: predicted[pick],
        measured_ms,
        budget_ms,
        within_budget: predicted[pick] <= budget_ms,
        eligible: candidates.len(),
        took_ms: started.elapsed().as_secs_f64() * 1e3,
        spent,
        reason: {
            let reason = match study {
                Some(_) => reason,
                None => format!("no search study in the bundle: the configured search, {reason}"),
            };
            if ruled_out > 0 {
                format!("{reason} ({left_out})")
            } else {
                reason
            }
        },
    })
}

/// The latency of one top-[`TOP_K`] `search` to `level` on `grey`, encoder included, in
/// milliseconds: run once, since every part of it ran while the rates were measured.
fn run_once(
    model: &Model,
    grey: &[u8],
    search: &SearchParams,
    level: u8,
) -> Result<f64, EngineError> {
    let options = PredictOptions {
        top_k: TOP_K,
        level: Some(level),
        mode_angle_deg: None,
        ..Default::default()
    };
    let clock = Instant::now();
    model
        .features(&[grey])
        .and_then(|f| model.predict_searching(&f, &options, search, &[None]))?;
    Ok(clock.elapsed().as_secs_f64() * 1e3)
}

/// [`estimate`], then, while a search predicted over the budget by at most [`RETIME_BEYOND`]
/// would be chosen were it within the budget, every measurement it is predicted from is timed
/// [`RETIMED_RUNS`] times more (the minimum kept), once a search and once a measurement, and
/// estimated again: a part that an earlier search had timed again is not timed a third time (on
/// a 2-core AMD Zen 3, where the served search is predicted near the budget, three or four
/// searches sharing their parts were timed again, and a calibration took 290–350 ms instead of
/// 160, docs/BENCHMARKS.md, 2026-12-07). Noise only
/// lengthens a timing, so a search whose prediction a slow timing pushed just over the budget is
/// not ruled out by it (on a 2-core AMD Zen 4 the most agreeing search was predicted 16.8–25.0 ms
/// over ten starts and, over 25 ms, gave way to another: the same choice in 8 of 10,
/// docs/RESULTS.md). Not past the deadline: a search is timed again only while the measuring
/// is within it.
fn estimate_and_retime(
    meter: &mut Meter,
    (candidates, rows, agreement): (&[Candidate], &[usize], &Agreement),
    (level, budget_ms): (u8, f64),
    (started, deadline_ms): (Instant, f64),
) -> (Vec<(f64, Option<Need>)>, bool) {
    let mut retimed = vec![false; candidates.len()];
    let mut timed_again = BTreeSet::new();
    loop {
        let (estimates, cut_short) = estimate(
            meter,
            candidates,
            agreement,
            (level, budget_ms),
            (started, deadline_ms),
        );
        let predicted = exact_predictions(&estimates);
        let in_time = !cut_short && started.elapsed().as_secs_f64() * 1e3 < deadline_ms;
        let next = in_time
            .then(|| retime_next(rows, agreement, &predicted, budget_ms, &retimed))
            .flatten();
        let Some(i) = next else {
            return (estimates, cut_short);
        };
        retimed[i] = true;
        meter.spent.retimed += 1;
        for need in parts(meter.model, &candidates[i].params, level) {
            if timed_again.insert(need) {
                meter.measure(need, true);
            }
        }
    }
}

/// Each prediction where it is exact, else infinity (a search left with a bound cannot be
/// chosen, see [`next_need`]).
fn exact_predictions(estimates: &[(f64, Option<Need>)]) -> Vec<f64> {
    estimates
        .iter()
        .map(|&(ms, need)| if need.is_none() { ms } else { f64::INFINITY })
        .collect()
}

/// The search to time again, if any (see [`estimate_and_retime`]): one not `retimed` yet,
/// predicted over `budget_ms` by at most [`RETIME_BEYOND`], that [`choose`] would pick were it
/// predicted at the budget; the most agreeing first.
fn retime_next(
    rows: &[usize],
    agreement: &Agreement,
    predicted: &[f64],
    budget_ms: f64,
    retimed: &[bool],
) -> Option<usize> {
    let mut order: Vec<usize> = (0..predicted.len()).collect();
    order.sort_by(|&a, &b| agreement.of[b].total_cmp(&agreement.of[a]));
    order.into_iter().find(|&i| {
        let near = predicted[i] > budget_ms && predicted[i] <= budget_ms * RETIME_BEYOND;
        near && !retimed[i] && {
            let mut at_budget = predicted.to_vec();
            at_budget[i] = budget_ms;
            choose(rows, agreement, &at_budget, budget_ms).0 == i
        }
    })
}

/// Each candidate's predicted latency, exact or (when it cannot be chosen) a lower bound with
/// what it still needs: `meter` measures what the candidates that may still be chosen need, the
/// lowest bound first, until every such candidate's prediction is exact, or, once `deadline_ms`
/// after `started` have passed, one is. Also what the measuring spent, and whether the deadline
/// cut it short.
fn estimate(
    meter: &mut Meter,
    candidates: &[Candidate],
    agreement: &Agreement,
    (level, budget_ms): (u8, f64),
    (started, deadline_ms): (Instant, f64),
) -> (Vec<(f64, Option<Need>)>, bool) {
    let model = meter.model;
    let emulated = |p: Precision| !model.fused.native(p);
    loop {
        let estimates: Vec<(f64, Option<Need>)> = candidates
            .iter()
            .map(|c| meter.rates.predict(model, &c.params, level, emulated))
            .collect();
        let any_exact = estimates.iter().any(|e| e.1.is_none());
        let past_deadline = started.elapsed().as_secs_f64() * 1e3 >= deadline_ms;
        match next_need(&estimates, agreement, budget_ms) {
            Some(_) if past_deadline && any_exact => return (estimates, true),
            Some(need) => meter.measure(need, false),
            None => return (estimates, false),
        }
    }
}

/// The measurement to make next, or `None` when none is needed: the one needed by the search
/// with the lowest bound among those that may still be chosen. `estimates` holds each
/// candidate's predicted latency, exact where its `Need` is `None`, else a lower bound. A search
/// with a bound cannot be chosen (by [`choose`], whatever its exact prediction, given the exact
/// ones) when some exact search is within the budget and it is not; or when, counted in, it would
/// agree less than the most agreeing such search (beyond the tie), or be bounded beyond [`TIE`]
/// times the fastest exact search within the budget that agrees as well (within the tie); or,
/// when no exact search is within the budget, when it is not either and is bounded beyond
/// [`TIE`] times the fastest exact search. Every bound is checked again after each measurement.
fn next_need(
    estimates: &[(f64, Option<Need>)],
    agreement: &Agreement,
    budget_ms: f64,
) -> Option<Need> {
    let exact: Vec<usize> = (0..estimates.len())
        .filter(|&i| estimates[i].1.is_none())
        .collect();
    let within: Vec<usize> = exact
        .iter()
        .copied()
        .filter(|&i| estimates[i].0 <= budget_ms)
        .collect();
    let most = agreement.most(&within);
    let fastest = |set: &mut dyn Iterator<Item = usize>| {
        set.map(|i| estimates[i].0).fold(f64::INFINITY, f64::min)
    };
    let fastest_exact = fastest(&mut exact.iter().copied());
    let may_win = |i: usize| {
        let bound = estimates[i].0;
        if within.is_empty() {
            return bound <= budget_ms || bound <= fastest_exact * TIE;
        }
        // The most agreeing, with this search counted in, and the fastest that tie with it.
        let most = most.max(agreement.of[i]);
        let rivals = fastest(&mut within.iter().copied().filter(|&j| agreement.ties(j, most)));
        bound <= budget_ms && agreement.ties(i, most) && bound <= rivals * TIE
    };
    (0..estimates.len())
        .filter(|&i| estimates[i].1.is_some() && may_win(i))
        .min_by(|&a, &b| estimates[a].0.total_cmp(&estimates[b].0))
        .and_then(|i| estimates[i].1)
}

/// Measures the costs of a search on this CPU on demand ([`Need`]), on the features of one grey
/// image, into [`Rates`]. Each measurement is the minimum of [`RUNS`] calls; the few rows are
/// timed before the many.
struct Meter<'a> {
    model: &'a Model,
    features: Vec<Vec<f32>>,
    /// [`TIMED_ROWS`] rotations spread over the search level; the first [`SMALL_ROWS`] of them
    /// are the few.
    many: Vec<[f32; 9]>,
    /// The finest full level up to the search level; [`TIMED_ROWS`] cells spread over it, of
    /// which the first [`SMALL_ROWS`] are the few.
    full: usize,
    cells: Vec<u64>,
    rates: Rates,
    spent: Spent,
}

impl<'a> Meter<'a> {
    /// Times the encoder on `grey` (its first call computes the features and warms it).
    fn new(model: &'a Model, grey: &[u8], level: u8) -> Result<Meter<'a>, EngineError> {
        let clock = Instant::now();
        let features = model.features(&[grey])?;
        let encoder = min_ms(RUNS, || {
            let _ = model.features(&[grey]);
        });
        let grid = model.grid_at(level)?;
        let spread = |len: usize| {
            let step = (len / TIMED_ROWS).max(1) as u64;
            (0..TIMED_ROWS as u64).map(move |i| (i * step) % len.max(1) as u64)
        };
        let many: Vec<[f32; 9]> = spread(grid.len())
            .map(|c| crate::so3::to_row_major_f32(&grid.rotation(c)))
            .collect();
        let full = (level as usize).min(model.projected.len().saturating_sub(1));
        let cells: Vec<u64> =
            spread(model.projected.get(full).map_or(0, |p| p.grid.len())).collect();
        Ok(Meter {
            model,
            features,
            many,
            full,
            cells,
            rates: Rates {
                encoder,
                row: BTreeMap::new(),
            },
            spent: Spent {
                encoder_ms: clock.elapsed().as_secs_f64() * 1e3,
                ..Spent::default()
            },
        })
    }

    /// Measures `need` for the first time, or (`again`) times it [`RETIMED_RUNS`] more times and
    /// keeps the minimum with what it measured before.
    fn measure(&mut self, need: Need, again: bool) {
        let Need(source, (precision, branches)) = need;
        let clock = Instant::now();
        let (model, features) = (self.model, &self.features);
        let runs = if again { RETIMED_RUNS } else { RUNS };
        let time = |few: bool, runs: usize| {
            let rows = if few { SMALL_ROWS } else { TIMED_ROWS };
            // One image's rows (the grey image's features).
            let rotations = [&self.many[..rows.min(self.many.len())]];
            let cells = &self.cells[..rows.min(self.cells.len())];
            min_ms(runs, || match source {
                Source::Encoded => {
                    let _ = model.score_rotations_by(features, &rotations, precision, branches);
                }
                Source::Projected => {
                    let _ = model.projected[self.full].log_weights_of_cells_by(
                        precision,
                        branches,
                        &features[0],
                        cells,
                    );
                }
            })
        };
        let timed = (time(true, runs), time(false, runs));
        let timed = match self.rates.row.get(&need) {
            Some(&(few, many)) => (few.min(timed.0), many.min(timed.1)),
            None => timed,
        };
        self.rates.row.insert(need, timed);
        self.spent.rows_ms += clock.elapsed().as_secs_f64() * 1e3;
        self.spent.measurements += 1;
    }
}

/// The candidate to serve and why: the most agreeing one predicted within `budget_ms` (within
/// the agreement's tie), else the fastest. Timings are noisy: searches predicted within [`TIE`]
/// of the fastest of a set count as equally fast, and the one scoring the fewest rows (a row of the
/// shape branch alone counting half) is taken,
/// so that the choice does not flip between starts; among those the lower prediction (twins in
/// other precisions score the same rows), then the study's order.
fn choose(
    rows: &[usize],
    agreement: &Agreement,
    predicted: &[f64],
    budget_ms: f64,
) -> (usize, String) {
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
    let most = agreement.most(&within);
    let most_agreeing: Vec<usize> = within
        .iter()
        .copied()
        .filter(|&i| agreement.ties(i, most))
        .collect();
    let all: Vec<usize> = (0..predicted.len()).collect();
    match fastest(&most_agreeing) {
        Some(i) => (
            i,
            format!(
                "the fastest of {} searches agreeing within {:.1} % of the most agreeing, among {} predicted within {budget_ms} ms",
                most_agreeing.len(),
                agreement.tie * 100.0,
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
    use super::{
        Agreement, Candidate, Need, Source, choose, next_need, retime_next, without_emulated_twins,
    };
    use crate::engine::SearchParams;
    use crate::net::{Branches, Precision};

    /// Agreements, with those within `tie` of each other counted as equal.
    fn agreed(of: &[f64], tie: f64) -> Agreement {
        Agreement {
            of: of.to_vec(),
            tie,
        }
    }

    fn search(start_level: u8, keep: usize, coarse_precision: Precision) -> Candidate {
        Candidate {
            params: SearchParams::halving(start_level, keep, coarse_precision),
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
        let (pick, _) = choose(
            &[1000, 1000],
            &agreed(&[1.0, 1.0], 0.0),
            &[20.0, 18.0],
            25.0,
        );
        assert_eq!(pick, 1);
    }

    #[test]
    fn a_search_and_its_rescoring_twin_predicted_17_percent_apart_tie() {
        // Measured on a 2-core Intel Xeon with AMX: the search predicted 15.2–16.4 ms, its twin
        // that rescores the finest level from 8-bit scores (64 rows more, in f32) 14.0 ms. The
        // one scoring fewer rows is served, however the noise orders the two.
        for slower in [15.2, 16.4] {
            let (pick, reason) = choose(
                &[3000, 3128],
                &agreed(&[1.0, 1.0], 0.01),
                &[slower, 14.0],
                25.0,
            );
            assert_eq!(pick, 0, "{slower} ms: {reason}");
        }
    }

    #[test]
    fn within_the_tie_fewer_rows_win_over_a_faster_prediction() {
        let (pick, _) = choose(&[1000, 800], &agreed(&[1.0, 1.0], 0.0), &[18.0, 20.0], 25.0);
        assert_eq!(pick, 1);
        // Out of the tie the faster one wins.
        let (pick, _) = choose(&[1000, 800], &agreed(&[1.0, 1.0], 0.0), &[15.0, 20.0], 25.0);
        assert_eq!(pick, 0);
    }

    #[test]
    fn a_search_is_measured_only_while_its_bound_may_still_win() {
        // Rows of a full level's projections, and rows encoded from rotations.
        let full = Some(Need(Source::Projected, (Precision::I8, Branches::Both)));
        let rows = Some(Need(Source::Encoded, (Precision::Bf16, Branches::Both)));
        // (estimates, agreement, the measurement expected next), budget 25 ms.
        let cases = [
            // An exact search at 10 ms: a bound beyond TIE × 10 with the same agreement is ruled
            // out; within it, the search is measured, the lowest bound first.
            (vec![(10.0, None), (13.0, full)], vec![1.0, 1.0], None),
            (vec![(10.0, None), (12.0, full)], vec![1.0, 1.0], full),
            (
                vec![(10.0, None), (11.0, full), (10.5, rows)],
                vec![1.0; 3],
                rows,
            ),
            // A more agreeing search is measured while its bound is within the budget, however
            // slow against the others; a less agreeing one never.
            (vec![(10.0, None), (20.0, full)], vec![0.99, 1.0], full),
            (vec![(10.0, None), (30.0, full)], vec![0.99, 1.0], None),
            (vec![(10.0, None), (5.0, full)], vec![1.0, 0.99], None),
            // Nothing exact within the budget: a bound within it is measured, and one beyond it
            // only while it may be the fastest.
            (vec![(40.0, None), (20.0, full)], vec![1.0, 1.0], full),
            (vec![(40.0, None), (45.0, full)], vec![1.0, 1.0], full),
            (vec![(40.0, None), (51.0, full)], vec![1.0, 1.0], None),
            // Nothing exact yet: everything may win.
            (vec![(90.0, rows), (50.0, full)], vec![1.0, 1.0], full),
        ];
        for (estimates, agreement, expected) in cases {
            assert_eq!(
                next_need(&estimates, &agreed(&agreement, 0.0), 25.0),
                expected,
                "{estimates:?} {agreement:?}"
            );
        }
    }

    #[test]
    fn a_search_predicted_just_over_the_budget_is_timed_again_if_it_would_win() {
        // The more agreeing search (two images of a 200-image study) predicted at 26 ms: over
        // the 25 ms budget, it would win within it, so it is timed again; at 40 ms (beyond
        // RETIME_BEYOND) or once timed again, not.
        let agreement = agreed(&[1.0, 0.99], 0.005);
        let rows = [1000, 800];
        assert_eq!(
            retime_next(&rows, &agreement, &[26.0, 15.0], 25.0, &[false, false]),
            Some(0)
        );
        assert_eq!(
            retime_next(&rows, &agreement, &[40.0, 15.0], 25.0, &[false, false]),
            None
        );
        assert_eq!(
            retime_next(&rows, &agreement, &[26.0, 15.0], 25.0, &[true, false]),
            None
        );
        // Within the budget, or one that would not win within it (it agrees less), never.
        assert_eq!(
            retime_next(&rows, &agreement, &[20.0, 15.0], 25.0, &[false, false]),
            None
        );
        assert_eq!(
            retime_next(
                &rows,
                &agreed(&[0.99, 1.0], 0.005),
                &[26.0, 15.0],
                25.0,
                &[false; 2]
            ),
            None
        );
    }

    #[test]
    fn agreement_first_within_the_budget_else_the_fastest() {
        let agreement = agreed(&[1.0, 0.99], 0.0);
        let (pick, reason) = choose(&[1000, 500], &agreement, &[20.0, 10.0], 25.0);
        assert_eq!(pick, 0, "{reason}");
        let (pick, reason) = choose(&[1000, 500], &agreement, &[40.0, 30.0], 25.0);
        assert_eq!(pick, 1, "{reason}");
        assert!(reason.contains("no search"), "{reason}");
    }

    #[test]
    fn agreements_one_studied_image_apart_count_as_equal() {
        // A 100-image study: 99 % and 100 % are one image apart, so the faster search is
        // chosen whether or not the slower, more agreeing one is predicted within the budget
        // (its prediction near the budget no longer flips the choice between starts).
        let one_image = agreed(&[1.0, 0.99], 0.01);
        for slower in [24.0, 26.0] {
            let (pick, reason) = choose(&[1000, 500], &one_image, &[slower, 15.0], 25.0);
            assert_eq!(pick, 1, "{slower} ms: {reason}");
        }
        // Two images apart, the more agreeing search still wins within the budget.
        let two_images = agreed(&[1.0, 0.98], 0.01);
        let (pick, reason) = choose(&[1000, 500], &two_images, &[24.0, 15.0], 25.0);
        assert_eq!(pick, 0, "{reason}");
        // Measuring follows the same rule: a slower search one image more agreeing is not
        // timed once a faster one is exact; two images more agreeing, it is.
        let full = Some(Need(Source::Projected, (Precision::F32, Branches::Both)));
        let estimates = [(15.0, None), (20.0, full)];
        assert_eq!(
            next_need(&estimates, &agreed(&[0.99, 1.0], 0.01), 25.0),
            None
        );
        assert_eq!(
            next_need(&estimates, &agreed(&[0.98, 1.0], 0.01), 25.0),
            full
        );
    }
}
