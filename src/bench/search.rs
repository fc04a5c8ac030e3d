//! The study of the coarse-to-fine search (`alignist-train bench`): for held-out renders, the
//! exhaustive argmax of the finest level (every cell scored), then, per candidate search (start
//! level, cells kept per level: a fixed number or the cells that hold a fraction of the level's
//! estimated mass), how often its top-1 lands in the argmax's cell or a neighbour, how often it
//! scores as high (on symmetric objects an equivalent mode's cell is as good), how far below the
//! maximum it ends on average, the mass it estimates to cover, and its latency with the encoder.

use std::time::Instant;

use crate::bundle::study::{Argmax, SearchStudy, StudiedSearch, StudyReference};
use crate::engine::{EngineError, Model, PredictOptions, RESCORED_CELLS, SearchParams};
use crate::net::Precision;
use crate::so3::metrics::quantile;
use crate::so3::{covering_radius, geodesic_angle, to_row_major_f32};

/// What one candidate search scored.
#[derive(Debug, Clone)]
pub struct SearchFigures {
    /// The search.
    pub params: SearchParams,
    /// Fraction of images whose top-1 is the exhaustive argmax's cell or a neighbour (centres
    /// within twice the level's covering radius).
    pub agreement: f64,
    /// Fraction of images whose top-1 scores within 0.01 of the exhaustive maximum (an equally
    /// good cell: on symmetric objects, the argmax of another equivalent mode).
    pub found_maximum: f64,
    /// Mean of the exhaustive maximum log-weight less the top-1's (0 when the search finds it).
    pub mean_gap: f64,
    /// Mean mass the search's finest cells are estimated to cover.
    pub covered_mass: f64,
    /// Median time of one call, encoder included, in milliseconds.
    pub p50_ms: f64,
    /// The images whose top-1 is not the argmax's cell or a neighbour, each with whether it
    /// still scores within 0.01 of the maximum (a near-tie, e.g. another cell of a ring of
    /// equivalents).
    pub disagreements: Vec<(usize, bool)>,
}

/// The searches the study compares: start level 1 or 2, keep 32–512, keeps chosen by mass, and
/// keeps that halve (wide where a wrong region is chosen, narrow inside the chosen ones) or
/// double at each finer level, all in f32; then the wider ones with the coarse levels in
/// bfloat16, in f16 and in 8-bit integers, and some of those with the finest level in the coarse
/// precision as well, rescored ([`SearchParams::rescore_finest`]); then start level 1 with
/// halving keeps in every precision (the fewest rows); last, halving searches whose coarse levels
/// are ranked by the shape branch alone ([`SearchParams::shape_only_to`], half a row's
/// arithmetic).
pub fn candidates() -> Vec<SearchParams> {
    let flat = |start_level, keep, keep_mass| SearchParams {
        start_level,
        keep,
        keep_mass,
        keep_taper: 1.0,
        coarse_precision: Precision::F32,
        rescore_finest: false,
        shape_only_to: None,
    };
    let mut out = Vec::new();
    for start_level in [1u8, 2] {
        for keep in [32usize, 64, 128, 256, 512] {
            out.push(flat(start_level, keep, None));
        }
        for mass in [0.99, 0.999] {
            out.push(flat(start_level, 512, Some(mass)));
        }
    }
    let tapered = |start_level, keep, keep_taper| SearchParams {
        keep_taper,
        ..flat(start_level, keep, None)
    };
    out.push(tapered(1, 512, 0.5));
    for keep in [256, 384, 512] {
        out.push(tapered(2, keep, 0.5));
    }
    for keep in [64, 128] {
        out.push(tapered(2, keep, 2.0));
    }
    let bf16 = |search: SearchParams| SearchParams {
        coarse_precision: Precision::Bf16,
        ..search
    };
    out.push(bf16(flat(1, 512, None)));
    for keep in [128, 256, 384, 512, 768] {
        out.push(bf16(flat(2, keep, None)));
    }
    out.push(bf16(flat(2, 768, Some(0.999))));
    // The f32 twins of the wide halving searches, for cores without native bfloat16.
    for keep in [768, 1024] {
        out.push(tapered(2, keep, 0.5));
    }
    out.push(tapered(1, 1024, 0.5));
    for keep in [512, 768, 1024] {
        out.push(bf16(tapered(2, keep, 0.5)));
    }
    // Half-precision twins, for cores with AVX-512 FP16 (where bfloat16 may be slow).
    let f16 = |search: SearchParams| SearchParams {
        coarse_precision: Precision::F16,
        ..search
    };
    out.push(f16(flat(1, 512, None)));
    for keep in [256, 512] {
        out.push(f16(flat(2, keep, None)));
    }
    for keep in [512, 1024] {
        out.push(f16(tapered(1, keep, 0.5)));
    }
    for keep in [512, 768, 1024] {
        out.push(f16(tapered(2, keep, 0.5)));
    }
    // 8-bit twins, for cores with AVX-512 VNNI (about twice f16's rate).
    let i8 = |search: SearchParams| SearchParams {
        coarse_precision: Precision::I8,
        ..search
    };
    for keep in [256, 512] {
        out.push(i8(flat(2, keep, None)));
    }
    for keep in [512, 1024] {
        out.push(i8(tapered(1, keep, 0.5)));
    }
    for keep in [512, 768, 1024, 1536] {
        out.push(i8(tapered(2, keep, 0.5)));
    }
    // The finest level in the coarse precision too, its best cells rescored in f32: the finest
    // level's rows (as many as all coarser ones together) at the reduced rate.
    let rescored = |search: SearchParams| SearchParams {
        rescore_finest: true,
        ..search
    };
    for precision in [i8, bf16, f16] {
        for keep in [256, 512] {
            out.push(rescored(precision(flat(2, keep, None))));
        }
        out.push(rescored(precision(tapered(2, 1024, 0.5))));
    }
    out.push(rescored(i8(tapered(2, 128, 2.0))));
    // The fewest rows: start level 1 (576) and halving keeps from 192–384, in every precision,
    // for cores whose head is too slow for the start level 2 searches within the budget.
    for keep in [192, 256, 384] {
        for precision in [i8, bf16, f16] {
            out.push(precision(tapered(1, keep, 0.5)));
        }
        out.push(tapered(1, keep, 0.5));
    }
    out.extend(shape_ranked());
    out
}

/// Halving searches whose coarse levels are ranked by the shape branch alone: to level 3 in
/// every precision, to levels 2 and 4 in i8 (the shipped model's choice on AVX2), from start
/// level 2 (keeps of 192–1024, one of them with its finest level rescored), and from start level
/// 2 with fewer rows for cores without VNNI (to level 2, also with narrower or faster-tapering
/// keeps; to level 4 with keeps of 384 and 512; and with the finest level rescored).
fn shape_ranked() -> Vec<SearchParams> {
    const EVERY_PRECISION: [Precision; 4] = [
        Precision::I8,
        Precision::Bf16,
        Precision::F16,
        Precision::F32,
    ];
    let halving = |start_level, keep, to, coarse_precision| SearchParams {
        shape_only_to: Some(to),
        ..SearchParams::halving(start_level, keep, coarse_precision)
    };
    let mut out = Vec::new();
    for keep in [256, 384, 512] {
        for precision in EVERY_PRECISION {
            out.push(halving(1, keep, 3, precision));
        }
    }
    for keep in [256, 384] {
        out.push(halving(1, keep, 2, Precision::I8));
    }
    for keep in [512, 768] {
        out.push(halving(1, keep, 4, Precision::I8));
    }
    for keep in [512, 1024] {
        out.push(halving(2, keep, 3, Precision::I8));
        out.push(halving(2, keep, 3, Precision::Bf16));
    }
    // Start level 2 in full with narrower keeps: a keep of 256 scores the same rows below level 2
    // as start level 1's keep of 512, and level 2's 4 608 cells in full (one pass over its
    // projections) instead of 576 + 4 096 gathered ones, a superset of them.
    for keep in [192, 256, 384] {
        for precision in EVERY_PRECISION {
            out.push(halving(2, keep, 3, precision));
        }
    }
    out.push(SearchParams {
        rescore_finest: true,
        ..halving(2, 256, 3, Precision::I8)
    });
    // For cores without VNNI, whose `VPMADDWD` kernel runs the 8-bit head at about a third of
    // VNNI's rate: with the 200-image study none of the searches above at 99 % fits 25 ms there
    // (keep 384 to level 3: 30.6 ms p50 under `ALIGNIST_KERNELS=avx2` on Zen 4, docs/RESULTS.md).
    // Fewer rows: only level 2 ranked by the shape branch (its finest level 512 rows, not 768),
    // and the finest level in i8 with its best cells rescored in f32.
    for keep in [256, 384] {
        out.push(halving(2, keep, 2, Precision::I8));
    }
    for (keep, to) in [(256, 2), (384, 2), (384, 3)] {
        out.push(SearchParams {
            rescore_finest: true,
            ..halving(2, keep, to, Precision::I8)
        });
    }
    // Every level below the finest ranked by the shape branch (level 4's rows at half the
    // arithmetic), and the widest keeps with their finest level rescored: the fewest rows a keep
    // of 384 or 512 scores.
    for keep in [384, 512] {
        let shape_to_4 = halving(2, keep, 4, Precision::I8);
        out.push(shape_to_4);
        out.push(SearchParams {
            rescore_finest: true,
            ..shape_to_4
        });
    }
    out.push(SearchParams {
        rescore_finest: true,
        ..halving(2, 512, 3, Precision::I8)
    });
    // Only level 2 ranked by the shape branch, with fewer rows below it: a keep of 192, and a
    // keep of 256 that tapers faster (level 4 and 5 rows cut by a quarter, or by half or more).
    out.push(halving(2, 192, 2, Precision::I8));
    for keep_taper in [0.375, 0.25] {
        out.push(SearchParams {
            keep_taper,
            ..halving(2, 256, 2, Precision::I8)
        });
    }
    out
}

/// Runs `searches` to `level` (top-`top_k`) on every crop and compares each with the exhaustive
/// argmax of `level`: `known[i]`, where given, is crop `i`'s (from a study written before: no
/// cell is scored for it, and a search's top-1 is scored alone in f32, as the exhaustive pass
/// scores it), else every cell of `level` is scored. Returns each search's figures and every
/// crop's reference.
pub fn study(
    model: &Model,
    crops: &[Vec<u8>],
    searches: &[SearchParams],
    (level, top_k): (u8, usize),
    known: &[Option<Argmax>],
) -> Result<(Vec<SearchFigures>, Vec<Argmax>), EngineError> {
    let grid = model.grid_at(level)?;
    let options = PredictOptions {
        top_k,
        level: Some(level),
        mode_angle_deg: None,
        ..Default::default()
    };
    let neighbour = 2.0 * covering_radius(level);
    let started = Instant::now();
    let mut agree = vec![0usize; searches.len()];
    let mut found = vec![0usize; searches.len()];
    let mut mass = vec![0.0f64; searches.len()];
    let mut gap = vec![0.0f64; searches.len()];
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); searches.len()];
    let mut disagreements: Vec<Vec<(usize, bool)>> = vec![Vec::new(); searches.len()];
    let mut references = Vec::with_capacity(crops.len());
    for (n, crop) in crops.iter().enumerate() {
        let features = model.features(&[crop])?.swap_remove(0);
        let (logits, best) = match known.get(n).copied().flatten() {
            Some(reference) => (None, reference),
            None => {
                let logits = model.logits_at(&features, level)?;
                let (cell, logit) = logits
                    .iter()
                    .enumerate()
                    .fold((0, f32::MIN), |b, (i, &l)| if l > b.1 { (i, l) } else { b });
                let cell = cell as u64;
                (Some(logits), Argmax { cell, logit })
            }
        };
        references.push(best);
        let best_rotation = grid.rotation(best.cell);
        let logit_of = |cell: u64| match &logits {
            Some(logits) => logits[cell as usize],
            None => {
                let rotation = to_row_major_f32(&grid.rotation(cell));
                let features = std::slice::from_ref(&features);
                model.score_rotations_many(features, &[vec![rotation]], Precision::F32)[0][0]
            }
        };
        for (s, search) in searches.iter().enumerate() {
            let t = Instant::now();
            let f = model.features(&[crop])?;
            let p = model
                .predict_searching(&f, &options, search, &[None])?
                .swap_remove(0);
            times[s].push(t.elapsed().as_secs_f64() * 1e3);
            let top = p.top[0].cell;
            let top_logit = logit_of(top);
            let tied = top_logit >= best.logit - 0.01;
            if geodesic_angle(&grid.rotation(top), &best_rotation) <= neighbour {
                agree[s] += 1;
            } else {
                disagreements[s].push((n, tied));
            }
            if tied {
                found[s] += 1;
            }
            mass[s] += p.covered_mass;
            gap[s] += f64::from(best.logit - top_logit);
        }
        eprint!(
            "\rsearch study: {}/{} images, {:.0} s",
            n + 1,
            crops.len(),
            started.elapsed().as_secs_f64()
        );
    }
    eprintln!();
    let n = crops.len().max(1) as f64;
    let figures = searches
        .iter()
        .enumerate()
        .map(|(s, &params)| SearchFigures {
            params,
            agreement: agree[s] as f64 / n,
            found_maximum: found[s] as f64 / n,
            mean_gap: gap[s] / n,
            covered_mass: mass[s] / n,
            p50_ms: quantile(&times[s], 0.5),
            disagreements: std::mem::take(&mut disagreements[s]),
        })
        .collect();
    Ok((figures, references))
}

/// The study as the record a bundle carries ([`SearchStudy`]), for the images rendered from
/// `seed` with their `references`, on the network whose sha256 is `network_sha256`, to `level`.
pub fn record(
    figures: &[SearchFigures],
    level: u8,
    seed: u64,
    command: String,
    network_sha256: Option<String>,
    references: Vec<StudyReference>,
) -> SearchStudy {
    SearchStudy {
        level,
        images: references.len(),
        command,
        seed: Some(seed),
        searches: figures.iter().map(studied_search).collect(),
        network_sha256,
        references,
        extended_by: Vec::new(),
    }
}

/// One search's figures as the study file holds them.
pub fn studied_search(f: &SearchFigures) -> StudiedSearch {
    StudiedSearch {
        start_level: f.params.start_level,
        keep: f.params.keep,
        keep_mass: f.params.keep_mass,
        keep_taper: f.params.keep_taper,
        coarse_precision: f.params.coarse_precision.name().into(),
        rescore_finest: f.params.rescores(),
        shape_only_to: f.params.shape_only_to,
        agreement: f.agreement,
        found_maximum: f.found_maximum,
    }
}

/// Whether `studied` is the study of the search `params` (a study records whether a search
/// rescores, [`SearchParams::rescores`], not the flag as given).
fn is_studied(studied: &StudiedSearch, params: &SearchParams) -> bool {
    let recorded = |p: SearchParams| SearchParams {
        rescore_finest: p.rescores(),
        ..p
    };
    SearchParams::of_studied(studied).is_some_and(|s| recorded(s) == recorded(*params))
}

/// The searches of `candidates` that `study` does not hold.
pub fn unstudied(study: &SearchStudy, candidates: &[SearchParams]) -> Vec<SearchParams> {
    candidates
        .iter()
        .filter(|c| !study.searches.iter().any(|s| is_studied(s, c)))
        .copied()
        .collect()
}

/// The sha256 of a crop's bytes, lower-case hex.
fn image_sha256(crop: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    hex::encode(Sha256::digest(crop))
}

/// Each crop's references as the study file holds them (`crops[i]` is `references[i]`'s).
pub fn study_references(crops: &[Vec<u8>], references: &[Argmax]) -> Vec<StudyReference> {
    crops
        .iter()
        .zip(references)
        .map(|(crop, &argmax)| StudyReference {
            image_sha256: image_sha256(crop),
            argmax,
        })
        .collect()
}

/// The exhaustive argmax `study` holds for each of `crops`, where it holds one for the same
/// image at the same place (`None` for the others: they are scored again).
pub fn known_references(study: &SearchStudy, crops: &[Vec<u8>]) -> Vec<Option<Argmax>> {
    crops
        .iter()
        .enumerate()
        .map(|(i, crop)| {
            let r = study.references.get(i)?;
            (r.image_sha256 == image_sha256(crop)).then_some(r.argmax)
        })
        .collect()
}

/// Prints the study as a table, then the default search's figures and its disagreements by
/// object (`objects[i]` names image `i`).
pub fn print(figures: &[SearchFigures], default: &SearchParams, objects: &[String]) {
    println!("search to level 5, top-10, against the exhaustive level-5 argmax:");
    println!(
        "  start  keep             coarse  ranked by   finest              agreement  found max  mean gap  covered mass  p50 (encoder incl.)"
    );
    for f in figures {
        let keep = f.params.keep_description();
        let finest = match f.params.rescores() {
            true => format!(
                "{}, {RESCORED_CELLS} in f32",
                f.params.coarse_precision.name()
            ),
            false => "f32".to_string(),
        };
        let ranked = match f.params.shape_only_to {
            Some(to) => format!("shape ≤{to}"),
            None => "both".to_string(),
        };
        println!(
            "  {:>5}  {keep:<16} {:<6}  {ranked:<10}  {finest:<18} {:>8.1} % {:>8.1} % {:>9.3} {:>12.4}  {:>8.1} ms",
            f.params.start_level,
            f.params.coarse_precision.name(),
            100.0 * f.agreement,
            100.0 * f.found_maximum,
            f.mean_gap,
            f.covered_mass,
            f.p50_ms
        );
    }
    if let Some(f) = figures.iter().find(|f| f.params == *default) {
        println!(
            "default search ({default}): agreement: {:.1} %, found max {:.1} %, mean gap {:.3}, covered mass {:.4}",
            100.0 * f.agreement,
            100.0 * f.found_maximum,
            f.mean_gap,
            f.covered_mass
        );
        let mut by_object: std::collections::BTreeMap<&str, (usize, usize)> = Default::default();
        for &(i, tied) in &f.disagreements {
            let name = objects.get(i).map_or("?", String::as_str);
            let entry = by_object.entry(name).or_default();
            entry.0 += 1;
            entry.1 += usize::from(tied);
        }
        let listed: Vec<String> = by_object
            .iter()
            .map(|(name, (n, tied))| format!("{name} {n} ({tied} within 0.01 of the maximum)"))
            .collect();
        println!(
            "default search's disagreements by object: {}",
            if listed.is_empty() {
                "none".to_string()
            } else {
                listed.join(", ")
            }
        );
    }
}

#[cfg(test)]
mod tests {
    use super::candidates;

    #[test]
    fn every_studied_search_is_studied_once() {
        let all = candidates();
        for (i, a) in all.iter().enumerate() {
            assert!(all[i + 1..].iter().all(|b| b != a), "studied twice: {a}");
        }
    }
}
