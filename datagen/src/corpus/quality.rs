//! The corpus build's reconstruction filter (`[check]` of a corpus TOML): each input's
//! reconstruction is checked ([`crate::geometry::consistency`]) before pairs are made from it; an
//! input whose static depth consistency, overall or across its worst stretch of frames
//! ([`CheckReport::score`]), is below `min_static_depth_consistency` is skipped with
//! the score and the reasons in the status table (never silently), and every input's report is
//! kept under `OUT/checks/` (one JSON per input key), where the corpus report reads the
//! distribution.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_float};
use crate::error::{Error, Result};
use crate::geometry::consistency::{CheckConfig, CheckReport, check_sequence};
use crate::io::sequence::Sequence;

/// Folder of the per-input check reports in a build's output folder.
pub const CHECKS_DIR: &str = "checks";

/// `[check]` of a corpus TOML.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct BuildCheckConfig {
    /// Skip inputs whose static depth consistency (overall, or across the worst frame boundary:
    /// a pose jump) is below this; absent: no input is checked.
    /// Valid: [0, 1].
    pub min_static_depth_consistency: Option<f64>,
    /// How the check measures (`[check.settings]`).
    #[serde(default)]
    pub settings: CheckConfig,
}

impl Validate for BuildCheckConfig {
    fn validate(&self) -> Checked {
        if let Some(min) = self.min_static_depth_consistency {
            check_float("min_static_depth_consistency", min, 0.0..=1.0)?;
        }
        self.settings.validate().map_err(|e| e.under("settings"))
    }
}

/// The file an input's report is kept in: its key with path separators replaced.
pub fn report_path(out: &Path, input_key: &str) -> PathBuf {
    let name: String = input_key.chars().map(|c| if c == '/' || c == '\\' { '~' } else { c }).collect();
    out.join(CHECKS_DIR).join(format!("{name}.json"))
}

/// Checks `sequence` when the build filters; writes its report and returns the skip reason when
/// it is below the threshold (`None`: keep it, or no filter configured).
pub fn filter(config: &BuildCheckConfig, out: &Path, input_key: &str, sequence: &Sequence) -> Result<Option<String>> {
    let Some(min) = config.min_static_depth_consistency else {
        return Ok(None);
    };
    let report = check_sequence(sequence, "corpus input", "as read by the corpus build", false, &config.settings);
    write_report(&report_path(out, input_key), &report)?;
    if report.score() >= min {
        return Ok(None);
    }
    let worst = match &report.worst_stretch {
        Some(s) if s.consistency < report.static_depth_consistency => {
            format!(", {:.3} across frames {} | {}", s.consistency, s.before, s.after)
        }
        _ => String::new(),
    };
    Ok(Some(format!(
        "reconstruction check: static_depth_consistency {:.3}{worst} below min_static_depth_consistency {min} ({})",
        report.static_depth_consistency,
        report.reasons.join("; ")
    )))
}

fn write_report(path: &Path, report: &CheckReport) -> Result<()> {
    let dir = path.parent().expect("under CHECKS_DIR");
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let temporary = path.with_extension("json.tmp");
    let json = serde_json::to_vec_pretty(report).expect("a report serialises");
    std::fs::write(&temporary, json).map_err(|e| Error::io(&temporary, e))?;
    std::fs::rename(&temporary, path).map_err(|e| Error::io(path, e))
}

/// The static depth consistency of every input checked by the build in `out`.
pub fn read_scores(out: &Path) -> Result<Vec<f64>> {
    let dir = out.join(CHECKS_DIR);
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut scores = Vec::new();
    for entry in std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))? {
        let path = entry.map_err(|e| Error::io(&dir, e))?.path();
        if path.extension().is_none_or(|e| e != "json") {
            continue;
        }
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let report: CheckReport = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(&path, "check report", format!("invalid JSON: {e}")))?;
        scores.push(report.static_depth_consistency);
    }
    Ok(scores)
}
