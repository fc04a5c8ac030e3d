//! `alignist-train results`: evaluation tables of bundles in Markdown.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

pub(crate) fn results_cmd(bundles: &[PathBuf]) -> Result<()> {
    use alignist::bundle::model::ModelManifest;
    let mut rows: Vec<(String, ModelManifest)> = Vec::new();
    for b in bundles {
        let path = b.join("manifest.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let m: ModelManifest =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        if m.evaluation.is_none() {
            bail!(
                "{}: evaluation: the bundle was not evaluated",
                path.display()
            );
        }
        let name = b
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        rows.push((name, m));
    }
    let ar = |s: &alignist::so3::metrics::MetricsSummary| {
        s.accuracy_at.first().map_or(f64::NAN, |a| a.1)
    };
    let mut objects: Vec<String> = Vec::new();
    for (_, m) in &rows {
        for (o, _) in &m.evaluation.as_ref().expect("checked").per_object {
            if !objects.contains(o) {
                objects.push(o.clone());
            }
        }
    }
    println!(
        "| model | object | images | LL | ceiling | spread ° | AR@30 | chance AR@30 | median ° |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for object in objects.iter().map(Some).chain([None]) {
        for (name, m) in &rows {
            let e = m.evaluation.as_ref().expect("checked");
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
            println!(
                "| {name} | {} | {} | {:.2} | {} | {:.1} | {:.2} | {} | {:.1} |",
                object.map_or("**mean**", |o| o.as_str()),
                summary.images,
                summary.log_likelihood,
                if object.is_none() {
                    format!("{:.2}", e.ll_ceiling)
                } else {
                    "".into()
                },
                summary.spread_deg,
                ar(summary),
                chance.map_or(String::new(), |c| format!("{c:.2}")),
                summary.median_error_deg
            );
        }
    }
    println!();
    println!(
        "| model | method | images | steps × batch × K | train wall | eval level | eval img/s |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (name, m) in &rows {
        let t = &m.provenance.train;
        let method = describe_method(&t.method, &t.network.encoding);
        let images: usize = m.objects.iter().map(|o| o.train_images).sum();
        let images = if images == 0 {
            "fresh renders".to_string()
        } else {
            images.to_string()
        };
        let e = m.evaluation.as_ref().expect("checked");
        println!(
            "| {name} | {method} | {images} | {} × {} × {} | {:.0} s | {} | {:.2} |",
            t.steps, t.batch, t.k, m.provenance.report.seconds, e.level, e.images_per_second
        );
    }
    Ok(())
}

/// The method as the results table names it, from what the bundle was trained with.
pub(crate) fn describe_method(
    method: &alignist::train::Method,
    encoding: &alignist::encoding::RotationEncoding,
) -> String {
    use alignist::encoding::RotationEncoding;
    use alignist::train::{ExpertBranches, MeasureLoss, Method, SamplingStrategy};
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
                SamplingStrategy::ModeFocused { .. } => "mode-focused",
                SamplingStrategy::Uniform => "random sampling",
            }
        ),
        Method::Ipdf => format!("ipdf ({encoding})"),
    }
}
