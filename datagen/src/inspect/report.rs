//! `datagen inspect DIR --report OUT.html`: one self-contained HTML page a person reads at a
//! glance: totals and per-dataset counts, failures by reason from the corpus status tables,
//! histograms (inline SVG) of the co-visible fraction and of the trajectory parameters
//! ([`crate::pairs::trajectory::PathParameters`]), and a grid of contact-sheet thumbnails of sampled
//! pairs (PNG data URIs) linked to their exports. A script on the page marks it ready in the DOM
//! once it has loaded (`data-report-ready`), which a headless browser test reads back.
//!
//! The same distributions, side by side for several corpora (spherical vs bank sampler), are
//! what `datagen trajectories stats` prints and plots ([`compare_corpora`]).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use image::RgbImage;
use schemas::{ClipRecord, InputStatus, ShardReader, TrajectoryRecord};

use crate::error::{Error, Result};
use crate::inspect::shards::{pair_id, shard_paths, sheet_columns};
use crate::pairs::trajectory::{PathParameters, path_parameters};
use foundation::camera::mat4_from_row_major;

/// Bins of every histogram: fine enough to show a shape on a few hundred pairs.
const HISTOGRAM_BINS: usize = 20;
/// Thumbnails are scaled down to at most this width (pixels) to keep the page small.
const THUMBNAIL_WIDTH: u32 = 480;
/// Frames per thumbnail (first and last of the clip).
const THUMBNAIL_FRAMES: usize = 2;
/// Default number of thumbnails on a report.
pub const DEFAULT_THUMBNAILS: usize = 12;

/// What goes on a report besides the statistics.
#[derive(Debug, Clone)]
pub struct ReportOptions {
    /// At most this many pair thumbnails (one per clip, in shard order).
    pub thumbnails: usize,
    /// Where the pairs were exported (`--export`); thumbnails link to
    /// `<export>/<pair id>/contact_sheet.png`, else to the shard holding the pair.
    pub export_dir: Option<PathBuf>,
}

impl Default for ReportOptions {
    fn default() -> Self {
        Self { thumbnails: DEFAULT_THUMBNAILS, export_dir: None }
    }
}

/// Summary statistics of a list of values.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct Distribution {
    /// Number of values.
    pub count: usize,
    /// Mean.
    pub mean: f64,
    /// Smallest value.
    pub min: f64,
    /// First quartile.
    pub q1: f64,
    /// Median.
    pub median: f64,
    /// Third quartile.
    pub q3: f64,
    /// Largest value.
    pub max: f64,
}

impl Distribution {
    /// Statistics of the finite values of `values` (quartiles by linear interpolation).
    pub fn of(values: &[f64]) -> Self {
        let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        if sorted.is_empty() {
            return Self::default();
        }
        sorted.sort_by(f64::total_cmp);
        let quantile = |q: f64| {
            let x = q * (sorted.len() - 1) as f64;
            let k = x.floor() as usize;
            let next = sorted[(k + 1).min(sorted.len() - 1)];
            sorted[k] + (next - sorted[k]) * (x - k as f64)
        };
        Self {
            count: sorted.len(),
            mean: sorted.iter().sum::<f64>() / sorted.len() as f64,
            min: sorted[0],
            q1: quantile(0.25),
            median: quantile(0.5),
            q3: quantile(0.75),
            max: sorted[sorted.len() - 1],
        }
    }
}

/// Per-pair values of one corpus, gathered from its shards.
#[derive(Debug, Clone, Default)]
pub struct CorpusValues {
    /// Shards read.
    pub shards: usize,
    /// Clips per dataset.
    pub clips: BTreeMap<String, usize>,
    /// Pairs per dataset.
    pub pairs: BTreeMap<String, usize>,
    /// Pairs per trajectory kind.
    pub kinds: BTreeMap<String, usize>,
    /// Pairs per pair kind (`monocular`, `multiview`).
    pub pair_kinds: BTreeMap<String, usize>,
    /// Multi-view pairs per camera pair (`source→target`).
    pub camera_pairs: BTreeMap<String, usize>,
    /// Co-visible fraction of every pair.
    pub covisible_fraction: Vec<f64>,
    /// Path parameters of every pair with a pivot distance (sampled and bank paths).
    pub parameters: Vec<PathParameters>,
}

impl CorpusValues {
    fn add(&mut self, record: &ClipRecord) {
        *self.clips.entry(record.dataset.clone()).or_default() += 1;
        *self.pairs.entry(record.dataset.clone()).or_default() += record.trajectories.len();
        let sources: Vec<_> = record.world_from_camera.iter().map(|m| mat4_from_row_major(m)).collect();
        for trajectory in &record.trajectories {
            *self.kinds.entry(trajectory.kind.as_str().to_owned()).or_default() += 1;
            *self.pair_kinds.entry(record.pair_kind.as_str().to_owned()).or_default() += 1;
            if let (schemas::PairKind::Multiview, Some(source), Some(target)) =
                (record.pair_kind, &record.source_camera, &record.target_camera)
            {
                *self.camera_pairs.entry(format!("{source}→{target}")).or_default() += 1;
            }
            self.covisible_fraction.push(trajectory.covisible_fraction);
            let novel: Vec<_> = trajectory.world_from_camera.iter().map(|m| mat4_from_row_major(m)).collect();
            if let Some(parameters) = path_parameters(&sources, &novel, trajectory.pivot_distance) {
                self.parameters.push(parameters);
            }
        }
    }

    /// The distributions compared across corpora: (name, unit, values).
    pub fn series(&self) -> Vec<(&'static str, &'static str, Vec<f64>)> {
        let of = |f: fn(&PathParameters) -> f64| self.parameters.iter().map(f).collect::<Vec<f64>>();
        vec![
            ("co-visible fraction", "fraction of pixels", self.covisible_fraction.clone()),
            ("azimuth span", "degrees", of(|p| p.azimuth_span_deg)),
            ("elevation span", "degrees", of(|p| p.elevation_span_deg)),
            ("radial change", "fraction of R", of(|p| p.radial_change)),
            ("path length", "units of R", of(|p| p.path_length)),
        ]
    }
}

/// Reads every shard under `dir` (or the shard `dir`), calling `each` on every clip.
fn for_each_clip(dir: &Path, mut each: impl FnMut(&Path, usize, &ClipRecord) -> Result<()>) -> Result<usize> {
    let shards = shard_paths(dir)?;
    for shard in &shards {
        for (row, record) in ShardReader::open(shard)?.enumerate() {
            each(shard, row, &record?)?;
        }
    }
    Ok(shards.len())
}

/// Gathers the per-pair values of the shards under `dir`.
pub fn corpus_values(dir: &Path) -> Result<CorpusValues> {
    let mut values = CorpusValues::default();
    values.shards = for_each_clip(dir, |_, _, record| {
        values.add(record);
        Ok(())
    })?;
    Ok(values)
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Standard base64 (RFC 4648, with padding), for data URIs.
pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], chunk.get(1).copied().unwrap_or(0), chunk.get(2).copied().unwrap_or(0)];
        let n = u32::from(b[0]) << 16 | u32::from(b[1]) << 8 | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Colours of the series of a comparison histogram, in order.
const SERIES_COLOURS: [&str; 4] = ["#3b7dd8", "#e0703a", "#3aa35b", "#9b59b6"];

/// An SVG histogram of one or more series over a shared range (bars side by side per bin),
/// with axis labels, a legend and each series' mean in the title line.
pub fn svg_histogram(title: &str, unit: &str, series: &[(&str, &[f64])]) -> String {
    let (width, height, margin) = (520.0, 240.0, 40.0);
    let finite = || series.iter().flat_map(|(_, v)| v.iter().copied()).filter(|v| v.is_finite());
    let (lo, hi) = finite().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let (lo, hi) = if lo.is_finite() { (lo, if hi > lo { hi } else { lo + 1.0 }) } else { (0.0, 1.0) };
    let counts: Vec<Vec<usize>> = series
        .iter()
        .map(|(_, values)| {
            let mut bins = vec![0usize; HISTOGRAM_BINS];
            for v in values.iter().filter(|v| v.is_finite()) {
                let b = (((v - lo) / (hi - lo)) * HISTOGRAM_BINS as f64) as usize;
                bins[b.min(HISTOGRAM_BINS - 1)] += 1;
            }
            bins
        })
        .collect();
    // Fractions per series, so corpora of different sizes compare.
    let fractions: Vec<Vec<f64>> = counts
        .iter()
        .map(|bins| {
            let total = bins.iter().sum::<usize>().max(1) as f64;
            bins.iter().map(|&c| c as f64 / total).collect()
        })
        .collect();
    let top = fractions.iter().flatten().copied().fold(0.0, f64::max).max(f64::MIN_POSITIVE);
    let plot_w = width - 2.0 * margin;
    let plot_h = height - 2.0 * margin;
    let bin_w = plot_w / HISTOGRAM_BINS as f64;
    let bar_w = bin_w / series.len().max(1) as f64;
    let mut svg = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" class=\"histogram\" width=\"{width}\" height=\"{height}\" \
         viewBox=\"0 0 {width} {height}\" font-family=\"sans-serif\" font-size=\"11\">\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\
         <text x=\"{margin}\" y=\"16\" font-size=\"13\" font-weight=\"bold\">{}</text>",
        escape(title)
    );
    for (s, bins) in fractions.iter().enumerate() {
        let colour = SERIES_COLOURS[s % SERIES_COLOURS.len()];
        for (b, &f) in bins.iter().enumerate() {
            let h = f / top * plot_h;
            let _ = write!(
                svg,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{h:.1}\" fill=\"{colour}\"/>",
                margin + b as f64 * bin_w + s as f64 * bar_w,
                margin + plot_h - h,
                bar_w.max(0.5)
            );
        }
        let mean = Distribution::of(series[s].1).mean;
        let _ = write!(
            svg,
            "<rect x=\"{:.1}\" y=\"24\" width=\"10\" height=\"10\" fill=\"{colour}\"/>\
             <text x=\"{:.1}\" y=\"33\">{} (n = {}, mean {mean:.3})</text>",
            margin + s as f64 * 240.0,
            margin + 14.0 + s as f64 * 240.0,
            escape(series[s].0),
            series[s].1.len()
        );
    }
    let axis_y = margin + plot_h;
    let _ = write!(
        svg,
        "<line x1=\"{margin}\" y1=\"{axis_y}\" x2=\"{:.1}\" y2=\"{axis_y}\" stroke=\"black\"/>\
         <text x=\"{margin}\" y=\"{:.1}\">{lo:.3}</text>\
         <text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{hi:.3}</text>\
         <text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>\
         <text x=\"12\" y=\"{:.1}\" transform=\"rotate(-90 12 {:.1})\" text-anchor=\"middle\">share of pairs</text></svg>",
        margin + plot_w,
        axis_y + 14.0,
        margin + plot_w,
        axis_y + 14.0,
        margin + plot_w / 2.0,
        axis_y + 28.0,
        escape(unit),
        margin + plot_h / 2.0,
        margin + plot_h / 2.0,
    );
    svg
}

/// `name n, name n, ...` of a count table, escaped (`none` when empty).
fn counts(table: &BTreeMap<String, usize>) -> String {
    if table.is_empty() {
        return "none".to_owned();
    }
    table.iter().map(|(k, n)| format!("{} {n}", escape(k))).collect::<Vec<_>>().join(", ")
}

/// The thumbnail of one pair: the clip's first and last frames × target, mask, conditioning.
fn thumbnail(record: &ClipRecord, trajectory: &TrajectoryRecord) -> Result<Vec<u8>> {
    let decode = |bytes: &[u8], what: &str| {
        image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .map_err(|e| Error::Image { context: format!("{}: {what}", record.clip_id), reason: e.to_string() })
    };
    let frames = record.num_frames();
    let mut picked: Vec<usize> = (0..THUMBNAIL_FRAMES).map(|k| k * frames.saturating_sub(1)).collect();
    picked.dedup();
    let mut rows = Vec::new();
    for &i in &picked {
        let target = decode(&record.frames[i], &format!("frames[{i}]"))?.to_rgb8();
        let mask = decode(&trajectory.covisible_mask[i], &format!("covisible_mask[{i}]"))?.to_luma8();
        let condition = match &trajectory.condition {
            Some(stored) => decode(&stored[i], &format!("condition[{i}]"))?.to_rgb8(),
            None => RgbImage::from_fn(target.width(), target.height(), |x, y| {
                if mask.get_pixel(x, y).0[0] > 0 { *target.get_pixel(x, y) } else { image::Rgb([0, 0, 0]) }
            }),
        };
        rows.push(vec![target, foundation::contact_sheet::mask_to_rgb(&mask), condition]);
    }
    let labels: Vec<String> = picked.iter().map(|i| format!("frame {i}")).collect();
    let columns = sheet_columns(record, false);
    let columns: Vec<&str> = columns.iter().map(String::as_str).collect();
    let mut sheet = foundation::contact_sheet::labelled_contact_sheet(&columns, &labels, &rows);
    if sheet.width() > THUMBNAIL_WIDTH {
        let height = (f64::from(sheet.height()) * f64::from(THUMBNAIL_WIDTH) / f64::from(sheet.width())).round() as u32;
        sheet = image::imageops::resize(&sheet, THUMBNAIL_WIDTH, height.max(1), image::imageops::FilterType::Triangle);
    }
    let mut bytes = std::io::Cursor::new(Vec::new());
    sheet
        .write_to(&mut bytes, image::ImageFormat::Png)
        .map_err(|e| Error::Image { context: format!("{}: thumbnail", record.clip_id), reason: e.to_string() })?;
    Ok(bytes.into_inner())
}

/// A link from `from_dir` (the report's folder) to `target`: relative when both are relative or
/// share a prefix, else absolute (`file://` pages follow both).
fn link(target: &Path) -> String {
    let absolute = std::path::absolute(target).unwrap_or_else(|_| target.to_owned());
    let mut url = String::from("file://");
    for c in absolute.display().to_string().chars() {
        match c {
            ' ' => url.push_str("%20"),
            '#' => url.push_str("%23"),
            '?' => url.push_str("%3F"),
            '%' => url.push_str("%25"),
            c => url.push(c),
        }
    }
    escape(&url)
}

/// What [`write_report`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReportSummary {
    /// Shards read.
    pub shards: usize,
    /// Clips over all shards.
    pub clips: usize,
    /// Training pairs over all shards.
    pub pairs: usize,
    /// Thumbnails on the page.
    pub thumbnails: usize,
    /// Status-table rows that are not ok.
    pub failures: usize,
}

/// Writes the HTML report of the corpus folder (or shard) `dir` to `out` (see module docs).
pub fn write_report(dir: &Path, out: &Path, options: &ReportOptions) -> Result<ReportSummary> {
    let mut values = CorpusValues::default();
    let mut thumbnails = Vec::new();
    values.shards = for_each_clip(dir, |shard, _, record| {
        values.add(record);
        if thumbnails.len() < options.thumbnails
            && let Some(trajectory) = record.trajectories.first()
        {
            let id = pair_id(record, trajectory);
            let target = match &options.export_dir {
                Some(export) => export.join(&id).join("contact_sheet.png"),
                None => shard.to_owned(),
            };
            let caption = match (&record.source_camera, &record.target_camera) {
                (Some(source), Some(target)) => format!("{id} ({} {source}→{target})", record.pair_kind.as_str()),
                _ => id,
            };
            thumbnails.push((caption, link(&target), base64(&thumbnail(record, trajectory)?)));
        }
        Ok(())
    })?;
    let status = if dir.join("status").is_dir() { Some(crate::corpus::build::read_corpus_status(dir)?) } else { None };

    let clips: usize = values.clips.values().sum();
    let pairs: usize = values.pairs.values().sum();
    let mut html = String::new();
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Corpus report: {title}</title>\
         <style>body{{font-family:sans-serif;margin:2em;max-width:1200px}}table{{border-collapse:collapse}}\
         td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}th{{background:#f0f0f0}}\
         td:first-child,th:first-child{{text-align:left}}.grid{{display:flex;flex-wrap:wrap;gap:12px}}\
         figure{{margin:0}}figcaption{{font-size:12px;max-width:{THUMBNAIL_WIDTH}px;word-break:break-all}}\
         .histograms{{display:flex;flex-wrap:wrap;gap:12px}}</style></head><body>\
         <h1>Corpus report</h1><p>{title}</p><p id=\"report-status\">loading</p>",
        title = escape(&dir.display().to_string())
    );
    let _ = write!(
        html,
        "<section id=\"totals\"><h2>Totals</h2><table><tr><th>dataset</th><th>clips</th><th>pairs</th></tr>"
    );
    for (dataset, n) in &values.clips {
        let _ = write!(html, "<tr><td>{}</td><td>{n}</td><td>{}</td></tr>", escape(dataset), values.pairs[dataset]);
    }
    let _ = write!(
        html,
        "<tr><th>total ({} shards)</th><th>{clips}</th><th>{pairs}</th></tr></table><p>Pairs by trajectory kind: {}</p>\
         <p id=\"pair-kinds\">Pairs by pair kind: {}</p><p id=\"camera-pairs\">Multi-view pairs by camera pair (source→target): {}</p></section>",
        values.shards,
        counts(&values.kinds),
        counts(&values.pair_kinds),
        counts(&values.camera_pairs)
    );
    let _ = write!(html, "<section id=\"failures\"><h2>Inputs and failures</h2>");
    let mut failures = 0;
    match &status {
        None => {
            let _ = write!(html, "<p>No status tables (not a corpus build folder).</p>");
        }
        Some(status) => {
            let count = |s: InputStatus| status.values().filter(|r| r.status == s).count();
            failures = status.values().filter(|r| r.status != InputStatus::Ok).count();
            let _ = write!(
                html,
                "<p>{} ok, {} skipped, {} failed.</p><table><tr><th>outcome: reason</th><th>inputs</th><th>example</th></tr>",
                count(InputStatus::Ok),
                count(InputStatus::Skipped),
                count(InputStatus::Failed)
            );
            let mut reasons: BTreeMap<String, (usize, String)> = BTreeMap::new();
            for record in status.values().filter(|r| r.status != InputStatus::Ok) {
                let key =
                    format!("{}: {}", record.status.as_str(), crate::inspect::shards::reason_kind(&record.reason));
                let entry = reasons.entry(key).or_insert_with(|| (0, record.input_key.clone()));
                entry.0 += 1;
            }
            for (reason, (n, example)) in &reasons {
                let _ = write!(html, "<tr><td>{}</td><td>{n}</td><td>{}</td></tr>", escape(reason), escape(example));
            }
            let _ = write!(html, "</table>");
        }
    }
    let checks = crate::corpus::quality::read_scores(dir)?;
    if !checks.is_empty() {
        let d = Distribution::of(&checks);
        let _ = write!(
            html,
            "</section><section id=\"checks\"><h2>Reconstruction checks</h2><p>{} inputs checked; static depth \
             consistency mean {:.3}, q1 {:.3}, median {:.3}, q3 {:.3} (inputs below the build's \
             min_static_depth_consistency are skipped and listed above)</p>",
            d.count, d.mean, d.q1, d.median, d.q3
        );
        html.push_str(&svg_histogram("static depth consistency", "share", &[("inputs", &checks)]));
    }
    let _ = write!(html, "</section><section id=\"histograms\"><h2>Distributions</h2><div class=\"histograms\">");
    for (name, unit, series) in values.series() {
        html.push_str(&svg_histogram(name, unit, &[("pairs", &series)]));
    }
    let _ = write!(
        html,
        "</div><table><tr><th>quantity</th><th>n</th><th>mean</th><th>q1</th><th>median</th><th>q3</th></tr>"
    );
    for (name, _, series) in values.series() {
        let d = Distribution::of(&series);
        let _ = write!(
            html,
            "<tr><td>{name}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td></tr>",
            d.count, d.mean, d.q1, d.median, d.q3
        );
    }
    let _ = write!(html, "</table></section><section id=\"thumbnails\"><h2>Sampled pairs</h2><div class=\"grid\">");
    for (id, href, data) in &thumbnails {
        let _ = write!(
            html,
            "<figure><a href=\"{href}\"><img src=\"data:image/png;base64,{data}\" alt=\"{id}\"></a>\
             <figcaption>{id}</figcaption></figure>",
            id = escape(id)
        );
    }
    let _ = writeln!(
        html,
        "</div></section><script>\
         window.addEventListener('load', function () {{\
           var sections = Array.prototype.map.call(document.querySelectorAll('section[id]'), function (s) {{ return s.id; }});\
           var images = Array.prototype.slice.call(document.images);\
           var broken = images.filter(function (i) {{ return !(i.complete && i.naturalWidth > 0); }}).length;\
           document.getElementById('report-status').textContent =\
             'ready: sections=' + sections.join(',') + '; images=' + images.length + '; broken=' + broken;\
           document.body.setAttribute('data-report-ready', broken === 0 ? 'ok' : 'broken-images');\
         }});</script></body></html>"
    );
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }
    std::fs::write(out, html).map_err(|e| Error::io(out, e))?;
    Ok(ReportSummary { shards: values.shards, clips, pairs, thumbnails: thumbnails.len(), failures })
}

/// `datagen trajectories stats`: the distributions of each corpus in `corpora` (label, folder)
/// side by side as text (n, mean, quartiles), and with `plots`, one SVG per quantity there
/// overlaying the corpora.
pub fn compare_corpora(corpora: &[(String, PathBuf)], plots: Option<&Path>) -> Result<String> {
    let gathered: Vec<(String, CorpusValues)> =
        corpora.iter().map(|(label, dir)| Ok((label.clone(), corpus_values(dir)?))).collect::<Result<_>>()?;
    let mut text = String::new();
    let _ = writeln!(
        text,
        "{:<22} {:<12} {:>6} {:>9} {:>9} {:>9} {:>9}",
        "quantity", "corpus", "n", "mean", "q1", "median", "q3"
    );
    let per_corpus: Vec<Vec<(&str, &str, Vec<f64>)>> = gathered.iter().map(|(_, v)| v.series()).collect();
    if let Some(dir) = plots {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    for q in 0..per_corpus.first().map_or(0, Vec::len) {
        let (name, unit, _) = &per_corpus[0][q];
        for ((label, _), series) in gathered.iter().zip(&per_corpus) {
            let d = Distribution::of(&series[q].2);
            let _ = writeln!(
                text,
                "{name:<22} {label:<12} {:>6} {:>9.4} {:>9.4} {:>9.4} {:>9.4}",
                d.count, d.mean, d.q1, d.median, d.q3
            );
        }
        if let Some(dir) = plots {
            let series: Vec<(&str, &[f64])> =
                gathered.iter().zip(&per_corpus).map(|((label, _), s)| (label.as_str(), s[q].2.as_slice())).collect();
            let path = dir.join(format!("{}.svg", name.replace([' ', '-'], "_")));
            std::fs::write(&path, svg_histogram(name, unit, &series)).map_err(|e| Error::io(&path, e))?;
        }
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (input, expected) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), expected);
        }
    }

    #[test]
    fn quartiles_interpolate() {
        let d = Distribution::of(&[4.0, 1.0, 3.0, 2.0, f64::NAN]);
        assert_eq!((d.count, d.min, d.max, d.median, d.mean), (4, 1.0, 4.0, 2.5, 2.5));
        assert_eq!((d.q1, d.q3), (1.75, 3.25));
    }
}
