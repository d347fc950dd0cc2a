//! Loading and checking the TOML configs (`datagen pairs|render|build|synth --config`): one
//! parser for all of them, whose errors name the file and the key on their first line
//! (`configs/x.toml: key `trajectory.azimuth_deg`: must be a finite number in [0, 180], got
//! inf (line 4)`), and the range checks every config's [`Validate`] is built from.
//!
//! A config is checked where it enters: when a file is loaded ([`load_toml`]) and, for configs a
//! caller builds in code, by the library function that takes it (then the error is a
//! [`Error::InvalidParameter`] naming the same key).

use std::fmt::Display;
use std::ops::{Bound, RangeBounds};
use std::path::Path;

use serde::de::DeserializeOwned;
use toml::de::{DeTable, DeValue};

use crate::error::{Error, Result};

/// A config value outside its documented range: the key as written in TOML (relative to the
/// config being checked) and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("parameter `{key}`: {reason}")]
pub struct KeyError {
    /// The key, with its tables joined by dots (`mesh.discontinuity_ratio`).
    pub key: String,
    /// What is wrong, with the value.
    pub reason: String,
}

impl KeyError {
    /// A [`KeyError`] for `key`.
    pub fn new(key: impl Into<String>, reason: impl Into<String>) -> Self {
        Self { key: key.into(), reason: reason.into() }
    }

    /// The same error seen from the enclosing table `table` (`table.key`).
    pub fn under(self, table: &str) -> Self {
        Self { key: format!("{table}.{}", self.key), ..self }
    }

    /// The error as found in the config file `path` whose text is `text` (adds the key's line).
    pub fn in_file(self, path: &Path, text: &str) -> Error {
        let (document, _) = DeTable::parse_recoverable(text);
        let reason = match key_offset(document.get_ref(), &self.key) {
            Some(offset) => format!("{} (line {})", self.reason, line_column(text, offset).0),
            None => self.reason,
        };
        Error::Config { path: path.to_owned(), key: self.key, reason }
    }
}

impl From<KeyError> for Error {
    fn from(error: KeyError) -> Self {
        Error::parameter(error.key, error.reason)
    }
}

/// The result of a config check.
pub type Checked = std::result::Result<(), KeyError>;

/// A config whose every field has a documented valid range.
pub trait Validate {
    /// Checks every field, naming the first key out of range (relative to this config).
    fn validate(&self) -> Checked;
}

fn bound(bound: Bound<&f64>) -> Option<(f64, bool)> {
    match bound {
        Bound::Included(&v) => Some((v, true)),
        Bound::Excluded(&v) => Some((v, false)),
        Bound::Unbounded => None,
    }
}

/// `value` must be finite and inside `range` (e.g. `0.0..=180.0`, or
/// `(Bound::Excluded(0.0), Bound::Unbounded)` for a positive number).
pub fn check_float(key: &str, value: f64, range: impl RangeBounds<f64>) -> Checked {
    let (low, high) = (bound(range.start_bound()), bound(range.end_bound()));
    let above = low.is_none_or(|(low, closed)| if closed { value >= low } else { value > low });
    let below = high.is_none_or(|(high, closed)| if closed { value <= high } else { value < high });
    if value.is_finite() && above && below {
        return Ok(());
    }
    let interval = format!(
        "{}{}, {}{}",
        low.map_or("(", |(_, closed)| if closed { "[" } else { "(" }),
        low.map_or("-∞".to_owned(), |(v, _)| v.to_string()),
        high.map_or("∞".to_owned(), |(v, _)| v.to_string()),
        high.map_or(")", |(_, closed)| if closed { "]" } else { ")" }),
    );
    Err(KeyError::new(key, format!("must be a finite number in {interval}, got {value}")))
}

/// An integer `value` must be inside `range` (inclusive bounds).
pub fn check_count(key: &str, value: impl Into<u64> + Display + Copy, min: u64, max: u64) -> Checked {
    let v: u64 = value.into();
    if (min..=max).contains(&v) {
        Ok(())
    } else if max == u64::MAX {
        Err(KeyError::new(key, format!("must be at least {min}, got {value}")))
    } else {
        Err(KeyError::new(key, format!("must be in [{min}, {max}], got {value}")))
    }
}

/// A path template (`/recon/{video_id}`) may only use the placeholders in `known`, with every
/// brace paired and some text: a typo (`{vidoe_id}`) would otherwise silently point every
/// video at a path that does not exist. The one check for every template key (corpus sources'
/// `reconstructions`, `pairs.depth_noise.second_depth`).
pub fn check_placeholders(key: &str, template: &str, known: &[&str]) -> Checked {
    let list = || known.iter().map(|k| format!("{{{k}}}")).collect::<Vec<_>>().join(", ");
    if template.trim().is_empty() {
        return Err(KeyError::new(key, format!("is empty (leave the key out, or name a path using {})", list())));
    }
    let mut rest = template;
    while let Some(open) = rest.find(['{', '}']) {
        if rest[open..].starts_with('}') {
            return Err(KeyError::new(key, format!("`}}` without an opening `{{` in `{template}`")));
        }
        let after = &rest[open + 1..];
        let Some(close) = after.find(['{', '}']).filter(|&i| after[i..].starts_with('}')) else {
            return Err(KeyError::new(key, format!("`{{` without a closing `}}` in `{template}`")));
        };
        let name = &after[..close];
        if !known.contains(&name) {
            return Err(KeyError::new(
                key,
                format!("unknown placeholder `{{{name}}}` in `{template}` (known: {})", list()),
            ));
        }
        rest = &after[close + 1..];
    }
    Ok(())
}

/// Reads the TOML config `path`, deserializes it and checks every field ([`Validate`]).
pub fn load_toml<T: DeserializeOwned + Validate>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_toml(path, &text)
}

/// [`load_toml`] on text already read from `path`.
pub fn parse_toml<T: DeserializeOwned + Validate>(path: &Path, text: &str) -> Result<T> {
    let config: T = toml::from_str(text).map_err(|e| toml_error(path, text, &e))?;
    config.validate().map_err(|e| e.in_file(path, text))?;
    Ok(config)
}

/// 1-based line and column of byte `offset` of `text`.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (before.matches('\n').count() + 1, before[line_start..].chars().count() + 1)
}

/// A toml error as `FILE: key `a.b`: message (line L, column C)`: toml's own rendering puts
/// the offending line on the fourth line; here the key comes first.
fn toml_error(path: &Path, text: &str, error: &toml::de::Error) -> Error {
    let message = error.message().lines().map(str::trim).filter(|l| !l.is_empty()).collect::<Vec<_>>().join("; ");
    let span = error.span().filter(|span| !span.is_empty());
    let (document, _) = DeTable::parse_recoverable(text);
    let mut key = span.as_ref().and_then(|span| key_at(document.get_ref(), span.start)).unwrap_or_default();
    // serde names a missing field only in its message; the span is its table's header.
    if let Some(field) = message.strip_prefix("missing field `").and_then(|m| m.split('`').next()) {
        key = if key.is_empty() { field.to_owned() } else { format!("{key}.{field}") };
    }
    let reason = match &span {
        Some(span) => {
            let (line, column) = line_column(text, span.start);
            format!("{message} (line {line}, column {column})")
        }
        None => message,
    };
    if key.is_empty() {
        let line = span.map_or(1, |span| line_column(text, span.start).0);
        return Error::invalid(path, format!("line {line}"), reason);
    }
    Error::Config { path: path.to_owned(), key, reason }
}

/// The dotted key path of the deepest key or value whose span holds byte `offset`.
fn key_at(table: &DeTable, offset: usize) -> Option<String> {
    for (key, value) in table.iter() {
        let name = key.get_ref().to_string();
        // Children first: a `[table]`'s own span is only its header.
        if let Some(inner) = value_key_at(value.get_ref(), offset) {
            return Some(if inner.starts_with('[') { format!("{name}{inner}") } else { format!("{name}.{inner}") });
        }
        if key.span().contains(&offset) || value.span().contains(&offset) {
            return Some(name);
        }
    }
    None
}

fn value_key_at(value: &DeValue, offset: usize) -> Option<String> {
    match value {
        DeValue::Table(table) => key_at(table, offset),
        DeValue::Array(items) => items.iter().enumerate().find_map(|(i, item)| {
            let inner = value_key_at(item.get_ref(), offset);
            match inner {
                Some(inner) if inner.starts_with('[') => Some(format!("[{i}]{inner}")),
                Some(inner) => Some(format!("[{i}].{inner}")),
                None => item.span().contains(&offset).then(|| format!("[{i}]")),
            }
        }),
        _ => None,
    }
}

/// Byte offset of the key `path` (`a.b`, `sources[1].root`) in the document, if written there.
fn key_offset(table: &DeTable, path: &str) -> Option<usize> {
    let (head, rest) = match path.find(['.', '[']) {
        Some(i) => (&path[..i], Some(&path[i..])),
        None => (path, None),
    };
    let (key, value) = table.get_key_value(head)?;
    let Some(rest) = rest else { return Some(key.span().start) };
    let mut value = value.get_ref();
    let mut rest = rest;
    while let Some(index) = rest.strip_prefix('[') {
        let (number, after) = index.split_once(']')?;
        value = value.as_array()?.get(number.parse::<usize>().ok()?)?.get_ref();
        rest = after;
    }
    match rest.strip_prefix('.') {
        Some(inner) => key_offset(value.as_table()?, inner),
        None => Some(key.span().start),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Inner {
        #[serde(default)]
        value: f64,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Outer {
        #[serde(default)]
        seed: u64,
        items: Vec<Inner>,
        #[serde(default)]
        table: Option<Inner>,
    }

    impl Validate for Outer {
        fn validate(&self) -> Checked {
            for (i, item) in self.items.iter().enumerate() {
                check_float("value", item.value, 0.0..=1.0).map_err(|e| e.under(&format!("items[{i}]")))?;
            }
            Ok(())
        }
    }

    fn first_line(text: &str) -> String {
        let error = parse_toml::<Outer>(Path::new("c.toml"), text).unwrap_err().to_string();
        error.lines().next().unwrap().to_owned()
    }

    #[test]
    fn errors_name_file_and_key_on_the_first_line() {
        for (text, start) in [
            ("[[items]]\n[table]\nvalue = \"x\"\n", "c.toml: key `table.value`: invalid type"),
            ("[[items]]\n[[items]]\nvalue = true\n", "c.toml: key `items[1].value`: invalid type"),
            ("[[items]]\n[table]\nvalue = 1\nbogus = 2\n", "c.toml: key `table.bogus`: unknown field"),
            ("seed = -1\n[[items]]\n", "c.toml: key `seed`: invalid value"),
            ("seed = 1\n", "c.toml: key `items`: missing field"),
            (
                "[[items]]\nvalue = 1.5\n",
                "c.toml: key `items[0].value`: must be a finite number in [0, 1], got 1.5 (line 2)",
            ),
            ("[[items]]\nvalue = nan\n", "c.toml: key `items[0].value`: must be a finite number in [0, 1], got NaN"),
            ("[[items]]\ntable.value = 3x\n", "c.toml: key `items[0].table.value`:"),
        ] {
            let line = first_line(text);
            assert!(line.starts_with(start), "{text:?}: {line}");
        }
    }

    #[test]
    fn ranges_and_placeholders() {
        assert!(check_float("k", f64::INFINITY, (Bound::Excluded(0.0), Bound::Unbounded)).is_err());
        assert!(check_float("k", 0.0, (Bound::Excluded(0.0), Bound::Unbounded)).is_err());
        assert!(check_float("k", 1e-9, (Bound::Excluded(0.0), Bound::Unbounded)).is_ok());
        assert!(check_float("k", 1.0, 0.0..1.0).unwrap_err().reason.contains("[0, 1)"));
        assert!(check_count("k", 0u32, 1, u64::MAX).unwrap_err().reason.contains("at least 1"));
        assert!(check_placeholders("k", "/d/{video_id}/{name}", &["video_id", "name"]).is_ok());
        assert!(check_placeholders("k", "/d/{vide_id}", &["video_id"]).unwrap_err().reason.contains("{vide_id}"));
        for bad in ["", "  ", "/d/{video_id", "/d/video_id}", "/d/{{video_id}", "/d/{vid{eo_id}"] {
            assert!(check_placeholders("k", bad, &["video_id"]).is_err(), "{bad:?}");
        }
    }
}
