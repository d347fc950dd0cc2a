//! Typed fields of the JSON files the dataset readers parse (DyCheck, Kubric-4D,
//! ParallelDomain-4D): each accessor checks one value and fails with an error naming the file and
//! the field's path in it (`camera.quaternions[3]`), so the readers stay a list of fields.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::error::{Error, Result};

/// A parsed JSON file, kept with its path for error messages.
#[derive(Debug, Clone)]
pub(crate) struct JsonFile {
    /// The file.
    pub path: PathBuf,
    /// Its content.
    pub value: Value,
}

impl JsonFile {
    /// Reads and parses `path`: a missing file is an I/O error naming it, bad JSON an error naming
    /// the file and `what` (the format's name for the file's content).
    pub fn read(path: &Path, what: &str) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let value =
            serde_json::from_str(&text).map_err(|e| Error::invalid(path, what, format!("invalid JSON: {e}")))?;
        Ok(Self { path: path.to_owned(), value })
    }

    /// The field at `label` (a dotted path into nested objects, `scene.resolution`); an error if
    /// any step is missing.
    pub fn get(&self, label: &str) -> Result<&Value> {
        self.find(label).ok_or_else(|| Error::invalid(&self.path, label, "missing"))
    }

    /// The field at `label`, if present.
    pub fn find(&self, label: &str) -> Option<&Value> {
        label.split('.').try_fold(&self.value, |value, key| value.get(key))
    }

    /// A finite number.
    pub fn f64(&self, label: &str) -> Result<f64> {
        number(&self.path, label, self.get(label)?)
    }

    /// A non-negative integer.
    pub fn u64(&self, label: &str) -> Result<u64> {
        integer(&self.path, label, self.get(label)?)
    }

    /// A list of exactly `n` finite numbers.
    pub fn vector(&self, label: &str, n: usize) -> Result<Vec<f64>> {
        numbers(&self.path, label, self.get(label)?, Some(n))
    }

    /// A list of strings.
    pub fn strings(&self, label: &str) -> Result<Vec<String>> {
        strings(&self.path, label, self.get(label)?)
    }

    /// A list of non-negative integers.
    pub fn integers(&self, label: &str) -> Result<Vec<u64>> {
        let value = self.get(label)?;
        let items = list(&self.path, label, value)?;
        items.iter().enumerate().map(|(i, v)| integer(&self.path, &format!("{label}[{i}]"), v)).collect()
    }
}

/// `value` as a list.
pub(crate) fn list<'a>(path: &Path, label: &str, value: &'a Value) -> Result<&'a Vec<Value>> {
    value.as_array().ok_or_else(|| Error::invalid(path, label, format!("expected a list, found `{value}`")))
}

/// `value` as a finite number.
pub(crate) fn number(path: &Path, label: &str, value: &Value) -> Result<f64> {
    value
        .as_f64()
        .filter(|v| v.is_finite())
        .ok_or_else(|| Error::invalid(path, label, format!("expected a finite number, found `{value}`")))
}

/// `value` as a non-negative integer (a float with an integer value, as numpy writes, is one).
pub(crate) fn integer(path: &Path, label: &str, value: &Value) -> Result<u64> {
    if let Some(n) = value.as_u64() {
        return Ok(n);
    }
    match value.as_f64() {
        Some(v) if v >= 0.0 && v.fract() == 0.0 && v < 2f64.powi(53) => Ok(v as u64),
        _ => Err(Error::invalid(path, label, format!("expected a non-negative integer, found `{value}`"))),
    }
}

/// `value` as a list of finite numbers, of length `n` when given.
pub(crate) fn numbers(path: &Path, label: &str, value: &Value, n: Option<usize>) -> Result<Vec<f64>> {
    let items = list(path, label, value)?;
    if let Some(n) = n.filter(|&n| n != items.len()) {
        return Err(Error::invalid(path, label, format!("expected {n} numbers, found {}", items.len())));
    }
    items.iter().enumerate().map(|(i, v)| number(path, &format!("{label}[{i}]"), v)).collect()
}

/// `value` as a list of strings.
pub(crate) fn strings(path: &Path, label: &str, value: &Value) -> Result<Vec<String>> {
    let items = list(path, label, value)?;
    items
        .iter()
        .enumerate()
        .map(|(i, v)| {
            v.as_str()
                .map(str::to_owned)
                .ok_or_else(|| Error::invalid(path, format!("{label}[{i}]"), format!("expected a string, found `{v}`")))
        })
        .collect()
}
