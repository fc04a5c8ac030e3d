//! The results tables of evaluated bundles (`alignist-train results`, `docs/RESULTS.md`): per
//! object and model, LL beside the grid's ceiling, spread, AR@30 beside the symmetry group's
//! chance, median error, the first mode's AR@30; then how each model was trained.

use std::fmt::Write;

use crate::bundle::model::ModelManifest;
use crate::so3::metrics::MetricsSummary;

/// The two Markdown tables of `rows` (name and manifest of each bundle; bundles without an
/// evaluation have no rows).
pub fn results_tables(rows: &[(String, ModelManifest)]) -> String {
    let mut out = metrics_table(rows);
    out.push('\n');
    out.push_str(&runs_table(rows));
    out
}

/// AR@30 of a summary (its first accuracy threshold).
fn ar30(s: &MetricsSummary) -> f64 {
    s.accuracy_at.first().map_or(f64::NAN, |a| a.1)
}

/// The first mode's AR@30 (DESIGN §2), blank for evaluations written before it was measured.
fn mode_ar30(s: &MetricsSummary) -> String {
    s.mode_accuracy_at
        .first()
        .map_or(String::new(), |a| format!("{:.2}", a.1))
}

/// Per object, then the mean: one row per model.
fn metrics_table(rows: &[(String, ModelManifest)]) -> String {
    let mut objects: Vec<String> = Vec::new();
    for (_, m) in rows {
        for (o, _) in m.evaluation.iter().flat_map(|e| &e.per_object) {
            if !objects.contains(o) {
                objects.push(o.clone());
            }
        }
    }
    let mut out = String::from(
        "| model | object | images | LL | ceiling | spread ° | AR@30 | chance AR@30 | median ° | first mode AR@30 |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
    );
    for object in objects.iter().map(Some).chain([None]) {
        for (name, m) in rows {
            let Some(e) = &m.evaluation else { continue };
            let summary = match object {
                Some(o) => match e.per_object.iter().find(|(n, _)| n == o) {
                    Some((_, s)) => s,
                    None => continue,
                },
                None => &e.overall,
            };
            let chance = match object {
                Some(o) => e.chance_ar30.iter().find(|c| &c.0 == o).map(|c| c.1),
                None if !e.chance_ar30.is_empty() => Some(
                    e.chance_ar30.iter().map(|c| c.1).sum::<f64>() / e.chance_ar30.len() as f64,
                ),
                None => None,
            };
            let ceiling = match object {
                None => format!("{:.2}", e.ll_ceiling),
                Some(_) => String::new(),
            };
            let _ = writeln!(
                out,
                "| {name} | {} | {} | {:.2} | {ceiling} | {:.1} | {:.2} | {} | {:.1} | {} |",
                object.map_or("**mean**", |o| o.as_str()),
                summary.images,
                summary.log_likelihood,
                summary.spread_deg,
                ar30(summary),
                chance.map_or(String::new(), |c| format!("{c:.2}")),
                summary.median_error_deg,
                mode_ar30(summary)
            );
        }
    }
    out
}

/// How each model was trained and evaluated.
fn runs_table(rows: &[(String, ModelManifest)]) -> String {
    let mut out = String::from(
        "| model | method | images | steps × batch × K | train wall | eval level | eval img/s |\n\
         |---|---|---|---|---|---|---|\n",
    );
    for (name, m) in rows {
        let Some(e) = &m.evaluation else { continue };
        let t = &m.provenance.train;
        let method = describe_method(&t.method, &t.network.encoding, t.k);
        let images: usize = m.objects.iter().map(|o| o.train_images).sum();
        let images = match images {
            0 => "fresh renders".to_string(),
            n => n.to_string(),
        };
        let _ = writeln!(
            out,
            "| {name} | {method} | {images} | {} × {} × {} | {:.0} s | {} | {:.2} |",
            t.steps, t.batch, t.k, m.provenance.report.seconds, e.level, e.images_per_second
        );
    }
    out
}

/// The method as the results table names it: mode-focused sampling with its share of the `k`
/// rotations when it is not the paper's 3/4.
fn describe_method(
    method: &crate::train::Method,
    encoding: &crate::encoding::RotationEncoding,
    k: usize,
) -> String {
    use crate::encoding::RotationEncoding;
    use crate::train::{ExpertBranches, MeasureLoss, Method, SamplingStrategy};
    let encoding = match encoding {
        RotationEncoding::Cube => "cube PE",
        RotationEncoding::Ipdf { .. } => "IPDF PE",
    };
    match method {
        Method::Alignist {
            loss,
            sampling,
            experts,
        } => format!(
            "alignist ({}{}, {}, {encoding})",
            match experts {
                ExpertBranches::Both => "",
                ExpertBranches::ShapeOnly => "shape expert only, ",
                ExpertBranches::FeatureOnly => "feature expert only, ",
            },
            match loss {
                MeasureLoss::Gkl => "GKL",
                MeasureLoss::L1 => "L1",
            },
            match sampling {
                SamplingStrategy::ModeFocused { focused, .. } if *focused == k * 3 / 4 => {
                    "mode-focused".to_string()
                }
                SamplingStrategy::ModeFocused { focused, .. } => {
                    format!("mode-focused {focused} of {k}")
                }
                SamplingStrategy::Uniform => "random sampling".to_string(),
            }
        ),
        Method::Ipdf => format!("ipdf ({encoding})"),
    }
}
