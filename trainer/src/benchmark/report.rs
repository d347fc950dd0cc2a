//! The benchmark's table: per scene and mean, the paper's published CogNVS rows beside ours,
//! a one-line summary, and the per-scene differences of two runs (`--compare`).

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::Dataset;
use crate::error::{Error, Result};

/// One row of metrics; a value is None where it was not computed (no weights, no masks). A
/// value may be infinite (the PSNR of a frame identical to its target, the mPSNR of one with no
/// co-visible pixel): means keep it, as the official codes' `np.mean` does, and the JSON writes
/// it as the string `"inf"` ([`non_finite`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// PSNR ↑ (dB).
    #[serde(default, with = "non_finite")]
    pub psnr: Option<f64>,
    /// SSIM ↑.
    #[serde(default, with = "non_finite")]
    pub ssim: Option<f64>,
    /// LPIPS ↓.
    #[serde(default, with = "non_finite")]
    pub lpips: Option<f64>,
    /// mPSNR ↑ over the co-visibility masks.
    #[serde(default, with = "non_finite")]
    pub masked_psnr: Option<f64>,
    /// mSSIM ↑.
    #[serde(default, with = "non_finite")]
    pub masked_ssim: Option<f64>,
    /// mLPIPS ↓.
    #[serde(default, with = "non_finite")]
    pub masked_lpips: Option<f64>,
}

/// An optional number in JSON, which has no infinity: finite values as numbers, ±∞ and NaN as
/// the strings `"inf"`, `"-inf"` and `"nan"` (how Python's `float()` reads them back), None as
/// null.
pub mod non_finite {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    /// A number or one of the strings.
    #[derive(Serialize, Deserialize)]
    #[serde(untagged)]
    enum Value {
        Number(f64),
        Text(String),
    }

    /// Writes `value`.
    pub fn serialize<S: Serializer>(value: &Option<f64>, serializer: S) -> Result<S::Ok, S::Error> {
        match value {
            Some(v) if v.is_finite() => serializer.serialize_some(&Value::Number(*v)),
            Some(v) => serializer.serialize_some(&Value::Text(v.to_string().to_lowercase())),
            None => serializer.serialize_none(),
        }
    }

    /// Reads a value written by [`serialize`].
    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<f64>, D::Error> {
        match Option::<Value>::deserialize(deserializer)? {
            None => Ok(None),
            Some(Value::Number(v)) => Ok(Some(v)),
            Some(Value::Text(text)) => match text.as_str() {
                "inf" => Ok(Some(f64::INFINITY)),
                "-inf" => Ok(Some(f64::NEG_INFINITY)),
                "nan" => Ok(Some(f64::NAN)),
                other => {
                    Err(serde::de::Error::custom(format!("`{other}` is not a number, \"inf\", \"-inf\" or \"nan\"")))
                }
            },
        }
    }
}

impl Metrics {
    /// From `trainer eval`'s row, infinite values kept.
    pub fn from_row(row: &crate::eval::score::VideoRow) -> Self {
        Self {
            psnr: Some(row.psnr),
            ssim: Some(row.ssim),
            lpips: row.lpips,
            masked_psnr: row.masked_psnr,
            masked_ssim: row.masked_ssim,
            masked_lpips: row.masked_lpips,
        }
    }

    /// The columns by name, in table order.
    pub fn columns(&self) -> [(&'static str, Option<f64>); 6] {
        [
            ("PSNR ↑", self.psnr),
            ("SSIM ↑", self.ssim),
            ("LPIPS ↓", self.lpips),
            ("mPSNR ↑", self.masked_psnr),
            ("mSSIM ↑", self.masked_ssim),
            ("mLPIPS ↓", self.masked_lpips),
        ]
    }

    /// The mean of each column over `rows` weighted by `weights` (rows without a value skipped;
    /// an infinite value makes the mean infinite, as `np.mean` over the frames does).
    pub fn weighted_mean<'a>(rows: impl Iterator<Item = (&'a Metrics, f64)> + Clone) -> Metrics {
        let column = |f: fn(&Metrics) -> Option<f64>| {
            let (sum, weight) = rows
                .clone()
                .filter_map(|(m, w)| f(m).map(|v| (v * w, w)))
                .fold((0.0, 0.0), |(s, t), (v, w)| (s + v, t + w));
            (weight > 0.0).then(|| sum / weight)
        };
        Metrics {
            psnr: column(|m| m.psnr),
            ssim: column(|m| m.ssim),
            lpips: column(|m| m.lpips),
            masked_psnr: column(|m| m.masked_psnr),
            masked_ssim: column(|m| m.masked_ssim),
            masked_lpips: column(|m| m.masked_lpips),
        }
    }
}

/// A published row of the CogNVS paper.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PaperRow {
    /// Which row (the reconstruction it was rendered from, where the paper gives several).
    pub row: String,
    /// Its metrics.
    pub metrics: Metrics,
    /// FID ↓.
    pub fid: f64,
    /// KID ↓.
    pub kid: f64,
}

/// The paper's CogNVS rows for `dataset`: Table 1 (Kubric-4D, ParallelDomain-4D), Table 2 and
/// the appendix's masked table (DyCheck, with MegaSAM and with MoSca reconstructions), as quoted
/// in issue 54.
pub fn paper_rows(dataset: Dataset) -> Vec<PaperRow> {
    let row = |name: &str, [psnr, ssim, lpips, fid, kid]: [f64; 5], masked: Option<[f64; 3]>| PaperRow {
        row: name.to_string(),
        metrics: Metrics {
            psnr: Some(psnr),
            ssim: Some(ssim),
            lpips: Some(lpips),
            masked_psnr: masked.map(|m| m[0]),
            masked_ssim: masked.map(|m| m[1]),
            masked_lpips: masked.map(|m| m[2]),
        },
        fid,
        kid,
    };
    match dataset {
        Dataset::Kubric4d => vec![row("CogNVS (paper, Table 1)", [22.63, 0.760, 0.232, 102.47, 0.008], None)],
        Dataset::Pardom4d => vec![row("CogNVS (paper, Table 1)", [24.34, 0.797, 0.302, 102.43, 0.033], None)],
        Dataset::Dycheck => vec![
            row("CogNVS, MegaSAM (paper, Table 2)", [15.19, 0.382, 0.622, 94.48, 0.030], Some([15.35, 0.549, 0.557])),
            row("CogNVS, MoSca (paper, Table 2)", [16.94, 0.449, 0.598, 92.83, 0.031], Some([17.33, 0.607, 0.530])),
        ],
    }
}

/// One scene's line of the table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneLine {
    /// The scene.
    pub scene: String,
    /// Frames scored.
    pub frames: usize,
    /// Its metrics.
    pub metrics: Metrics,
    /// PSNR of the render alone over the pixels it covers (what a sampler that kept every
    /// rendered pixel would score there); None where the render is exact or covers nothing.
    pub render_psnr: Option<f64>,
}

/// A scene that could not be evaluated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FailedScene {
    /// The scene.
    pub scene: String,
    /// Why.
    pub reason: String,
}

/// `OUT/report.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// The dataset.
    pub dataset: Dataset,
    /// The protocol (`gcd` or `dycheck`).
    pub protocol: String,
    /// (width, height) the metrics were computed at.
    pub eval_size: (u32, u32),
    /// Whether that is the protocol's own size (otherwise the paper's numbers do not compare).
    pub protocol_size: bool,
    /// Every setting (see `settings.json`).
    pub settings: serde_json::Value,
    /// blake3 of the checkpoint folder (and LoRA file) evaluated.
    pub checkpoint_digest: String,
    /// The toolkit's commit (`git describe`), where the source tree was found.
    pub toolkit_commit: Option<String>,
    /// Seed of every sampling draw.
    pub seed: u64,
    /// Per scene evaluated, in order.
    pub scenes: Vec<SceneLine>,
    /// The scenes that failed, with the reason.
    pub failed: Vec<FailedScene>,
    /// Mean over every frame of every scene.
    pub mean: Metrics,
    /// FID over every frame of every scene.
    pub fid: Option<f64>,
    /// KID over every frame of every scene.
    pub kid: Option<f64>,
    /// KID's subset size used (clean-fid: the configured size, at most the frames there are).
    pub kid_subset_size: Option<usize>,
    /// The paper's published rows for this dataset.
    pub paper: Vec<PaperRow>,
    /// The one-line summary.
    pub summary: String,
}

fn cell(value: Option<f64>, digits: usize) -> String {
    value.map_or("–".to_string(), |v| format!("{v:.digits$}"))
}

/// The columns shown: those with a value in the mean or in a paper row.
fn shown(report: &Report) -> Vec<usize> {
    (0..6)
        .filter(|&i| {
            report.mean.columns()[i].1.is_some() || report.scenes.iter().any(|s| s.metrics.columns()[i].1.is_some())
        })
        .collect()
}

/// The report as Markdown: the scene table with the mean, FID/KID, the paper's rows beside the
/// mean, the failed scenes and the summary line.
pub fn markdown(report: &Report) -> String {
    let columns = shown(report);
    let names: Vec<&str> = columns.iter().map(|&i| Metrics::default().columns()[i].0).collect();
    let mut out = format!(
        "## CogNVS benchmark: {} ({} protocol, {}×{}{})\n\n",
        report.dataset.title(),
        report.protocol,
        report.eval_size.0,
        report.eval_size.1,
        if report.protocol_size { "" } else { ", NOT the protocol's size" }
    );
    out += &format!("| scene | frames | {} | render PSNR |\n", names.join(" | "));
    out += &format!("|---|---:|{}---:|\n", "---:|".repeat(columns.len()));
    for line in &report.scenes {
        let m = line.metrics.columns();
        let cells: Vec<String> = columns.iter().map(|&i| cell(m[i].1, 4)).collect();
        out +=
            &format!("| {} | {} | {} | {} |\n", line.scene, line.frames, cells.join(" | "), cell(line.render_psnr, 2));
    }
    let m = report.mean.columns();
    let cells: Vec<String> = columns.iter().map(|&i| cell(m[i].1, 4)).collect();
    let frames: usize = report.scenes.iter().map(|s| s.frames).sum();
    out += &format!("| **mean** | {frames} | {} | |\n\n", cells.join(" | "));
    out += &format!(
        "FID ↓ {}, KID ↓ {} (over every frame of every scene{})\n\n",
        cell(report.fid, 2),
        cell(report.kid, 4),
        report.kid_subset_size.map_or(String::new(), |n| format!("; KID subsets of {n}"))
    );
    out += "| | PSNR ↑ | SSIM ↑ | LPIPS ↓ | FID ↓ | KID ↓ | mPSNR ↑ | mSSIM ↑ | mLPIPS ↓ |\n";
    out += "|---|---:|---:|---:|---:|---:|---:|---:|---:|\n";
    let row = |name: &str, m: &Metrics, fid: Option<f64>, kid: Option<f64>| {
        format!(
            "| {name} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            cell(m.psnr, 2),
            cell(m.ssim, 3),
            cell(m.lpips, 3),
            cell(fid, 2),
            cell(kid, 3),
            cell(m.masked_psnr, 2),
            cell(m.masked_ssim, 3),
            cell(m.masked_lpips, 3)
        )
    };
    out += &row("**ours**", &report.mean, report.fid, report.kid);
    for paper in &report.paper {
        out += &row(&paper.row, &paper.metrics, Some(paper.fid), Some(paper.kid));
    }
    if !report.failed.is_empty() {
        out += "\nFailed scenes:\n\n";
        for failed in &report.failed {
            out += &format!("- {}: {}\n", failed.scene, failed.reason.replace('\n', " "));
        }
    }
    out += &format!(
        "\ncheckpoint blake3 {}, seed {}, toolkit {}\n\n{}\n",
        report.checkpoint_digest,
        report.seed,
        report.toolkit_commit.as_deref().unwrap_or("unknown"),
        report.summary
    );
    out
}

/// The plot-free summary line: scenes, the mean's metrics, FID/KID and the paper's first row.
pub fn summary(report: &Report) -> String {
    let metrics = |m: &Metrics, fid: Option<f64>, kid: Option<f64>| {
        let mut parts: Vec<String> =
            m.columns().iter().filter_map(|(n, v)| v.map(|v| format!("{} {v:.3}", short(n)))).collect();
        parts.extend(fid.map(|v| format!("FID {v:.2}")));
        parts.extend(kid.map(|v| format!("KID {v:.3}")));
        parts.join(" ")
    };
    let mut line = format!(
        "{}: {}/{} scenes, {}",
        report.dataset.name(),
        report.scenes.len(),
        report.scenes.len() + report.failed.len(),
        metrics(&report.mean, report.fid, report.kid)
    );
    if let Some(paper) = report.paper.first() {
        line += &format!(" | {}: {}", paper.row, metrics(&paper.metrics, Some(paper.fid), Some(paper.kid)));
    }
    if !report.protocol_size {
        line += " | evaluated at another size than the protocol's: not comparable to the paper";
    }
    line
}

/// A column's name without its arrow.
fn short(name: &str) -> &str {
    name.split(' ').next().unwrap_or(name)
}

/// Reads `DIR/report.json` of a finished benchmark.
pub fn read_report(dir: &Path) -> Result<Report> {
    let path = dir.join(super::REPORT_JSON);
    let text = std::fs::read_to_string(&path).map_err(|error| Error::Io { path: path.clone(), error })?;
    serde_json::from_str(&text).map_err(|e| Error::InvalidInput {
        path,
        what: "benchmark report".to_string(),
        reason: e.to_string(),
    })
}

/// The per-scene differences of run B from run A.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Comparison {
    /// The two folders.
    pub runs: (String, String),
    /// The dataset and protocol both used.
    pub protocol: String,
    /// Settings that differ between the runs (key: A's value → B's).
    pub differing_settings: BTreeMap<String, (serde_json::Value, serde_json::Value)>,
    /// Per scene: B − A of each metric.
    pub scenes: Vec<(String, Metrics)>,
    /// B − A of the means.
    pub mean: Metrics,
    /// B − A of FID and KID.
    pub fid: Option<f64>,
    /// B − A of KID.
    pub kid: Option<f64>,
}

fn difference(a: &Metrics, b: &Metrics) -> Metrics {
    // Equal values differ by 0, the same infinity included (∞ − ∞ would be NaN).
    let d = |x: Option<f64>, y: Option<f64>| {
        let (x, y) = (x?, y?);
        Some(if x == y { 0.0 } else { y - x })
    };
    Metrics {
        psnr: d(a.psnr, b.psnr),
        ssim: d(a.ssim, b.ssim),
        lpips: d(a.lpips, b.lpips),
        masked_psnr: d(a.masked_psnr, b.masked_psnr),
        masked_ssim: d(a.masked_ssim, b.masked_ssim),
        masked_lpips: d(a.masked_lpips, b.masked_lpips),
    }
}

/// Compares two benchmark folders, refusing (naming both) when their dataset, protocol or eval
/// size differ, or when they did not evaluate the same scenes.
pub fn compare(a: &Path, b: &Path) -> Result<Comparison> {
    let (ra, rb) = (read_report(a)?, read_report(b)?);
    let refuse = |reason: String| Error::InvalidArgument { name: "compare".to_string(), reason };
    let protocol =
        |r: &Report| format!("{} ({} protocol at {}×{})", r.dataset.name(), r.protocol, r.eval_size.0, r.eval_size.1);
    if protocol(&ra) != protocol(&rb) {
        return Err(refuse(format!(
            "{} is {} but {} is {}: only runs of one protocol compare",
            a.display(),
            protocol(&ra),
            b.display(),
            protocol(&rb)
        )));
    }
    let names = |r: &Report| r.scenes.iter().map(|s| s.scene.clone()).collect::<Vec<_>>();
    let (na, nb) = (names(&ra), names(&rb));
    if na != nb {
        let only_a: Vec<&String> = na.iter().filter(|s| !nb.contains(s)).collect();
        let only_b: Vec<&String> = nb.iter().filter(|s| !na.contains(s)).collect();
        return Err(refuse(format!(
            "the runs evaluated different scenes: only in {}: {only_a:?}; only in {}: {only_b:?} (finish both \
             on the same --scenes, or rerun the failed ones)",
            a.display(),
            b.display()
        )));
    }
    let mut differing = BTreeMap::new();
    if let (Some(sa), Some(sb)) = (ra.settings.as_object(), rb.settings.as_object()) {
        for key in sa.keys().chain(sb.keys()) {
            let (va, vb) = (sa.get(key).cloned().unwrap_or_default(), sb.get(key).cloned().unwrap_or_default());
            if va != vb {
                differing.insert(key.clone(), (va, vb));
            }
        }
    }
    let scenes =
        ra.scenes.iter().zip(&rb.scenes).map(|(x, y)| (x.scene.clone(), difference(&x.metrics, &y.metrics))).collect();
    Ok(Comparison {
        runs: (a.display().to_string(), b.display().to_string()),
        protocol: protocol(&ra),
        differing_settings: differing,
        scenes,
        mean: difference(&ra.mean, &rb.mean),
        fid: ra.fid.zip(rb.fid).map(|(x, y)| y - x),
        kid: ra.kid.zip(rb.kid).map(|(x, y)| y - x),
    })
}

/// The comparison as Markdown: B − A per scene and of the mean (↑/↓ say which sign is better).
pub fn comparison_markdown(c: &Comparison) -> String {
    let columns: Vec<usize> = (0..6)
        .filter(|&i| c.mean.columns()[i].1.is_some() || c.scenes.iter().any(|s| s.1.columns()[i].1.is_some()))
        .collect();
    let names: Vec<&str> = columns.iter().map(|&i| Metrics::default().columns()[i].0).collect();
    let mut out = format!("## B − A: B = {}, A = {} ({})\n\n", c.runs.1, c.runs.0, c.protocol);
    out += &format!("| scene | {} |\n|---|{}\n", names.join(" | "), "---:|".repeat(columns.len()));
    let signed = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:+.4}"));
    for (scene, m) in c.scenes.iter().chain(std::iter::once(&("**mean**".to_string(), c.mean.clone()))) {
        let m = m.columns();
        let cells: Vec<String> = columns.iter().map(|&i| signed(m[i].1)).collect();
        out += &format!("| {scene} | {} |\n", cells.join(" | "));
    }
    out += &format!("\nFID ↓ {}, KID ↓ {}\n", signed(c.fid), signed(c.kid));
    if !c.differing_settings.is_empty() {
        out += "\nSettings that differ (A → B):\n\n";
        for (key, (a, b)) in &c.differing_settings {
            out += &format!("- {key}: {a} → {b}\n");
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An infinite value (identical frames) survives the row, the frame-weighted mean, the JSON
    /// and the table, and two equal infinities differ by 0.
    #[test]
    fn infinite_values_are_kept() {
        let row = crate::eval::score::VideoRow {
            name: "v".to_string(),
            frames: 2,
            sample: None,
            psnr: f64::INFINITY,
            ssim: 1.0,
            lpips: Some(0.0),
            masked_psnr: Some(f64::INFINITY),
            masked_ssim: Some(1.0),
            masked_lpips: Some(0.0),
        };
        let infinite = Metrics::from_row(&row);
        assert_eq!(infinite.psnr, Some(f64::INFINITY));
        let finite = Metrics { psnr: Some(20.0), ssim: Some(0.5), ..Default::default() };
        let mean = Metrics::weighted_mean([(&infinite, 1.0), (&finite, 3.0)].into_iter());
        assert_eq!((mean.psnr, mean.masked_psnr), (Some(f64::INFINITY), Some(f64::INFINITY)));
        let json = serde_json::to_string(&mean).unwrap();
        assert!(json.contains(r#""psnr":"inf""#), "{json}");
        assert_eq!(serde_json::from_str::<Metrics>(&json).unwrap(), mean);
        let bad = serde_json::from_str::<Metrics>(r#"{"psnr": "big"}"#).unwrap_err().to_string();
        assert!(bad.contains("big"), "{bad}");
        assert_eq!(cell(mean.psnr, 4), "inf");
        assert_eq!(difference(&mean, &mean).psnr, Some(0.0));
        assert_eq!(difference(&finite, &mean).psnr, Some(f64::INFINITY));
    }
}
