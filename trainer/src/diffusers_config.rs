//! Reading diffusers `config.json` files into serde structs whose fields use the upstream names:
//! parse, validate (errors name the file and field), and report keys the struct does not know
//! (kept in its `extra` map, never silently dropped).

use std::collections::BTreeMap;
use std::path::Path;

use serde::de::DeserializeOwned;

use crate::error::{Error, Result};

/// A diffusers configuration struct.
pub trait DiffusersConfig: DeserializeOwned {
    /// What the config describes, for messages ("VAE", "scheduler").
    const KIND: &'static str;
    /// File name inside a model folder (`config.json`, `scheduler_config.json`).
    const FILE_NAME: &'static str;

    /// Rejects invalid values and combinations, naming the field; `source_name` names the file.
    fn validate(&self, source_name: &str) -> Result<()>;

    /// Keys the struct does not know, as parsed.
    fn extra(&self) -> &BTreeMap<String, serde_json::Value>;

    /// Keys that are neither fields nor diffusers metadata (`_…`).
    fn unknown_keys(&self) -> Vec<&str> {
        self.extra().keys().filter(|k| !k.starts_with('_')).map(String::as_str).collect()
    }

    /// Parses and validates a config; `source_name` names it in errors.
    fn from_json_str(json: &str, source_name: &str) -> Result<Self> {
        parse(json, source_name)
    }

    /// Reads a config file (or the [`DiffusersConfig::FILE_NAME`] in a folder); unknown keys are
    /// printed to stderr as a warning and kept.
    fn from_json_file(path: impl AsRef<Path>) -> Result<Self> {
        read(path.as_ref())
    }
}

/// Parses and validates a config; `source_name` names it in errors.
pub fn parse<T: DiffusersConfig>(json: &str, source_name: &str) -> Result<T> {
    let config: T = serde_json::from_str(json).map_err(|e| Error::InvalidConfig {
        source_name: source_name.to_string(),
        field: "(json)".to_string(),
        reason: e.to_string(),
    })?;
    config.validate(source_name)?;
    Ok(config)
}

/// Reads a config file (or the [`DiffusersConfig::FILE_NAME`] in a folder); unknown keys are
/// printed to stderr as a warning.
pub fn read<T: DiffusersConfig>(path: &Path) -> Result<T> {
    let path = if path.is_dir() { path.join(T::FILE_NAME) } else { path.to_path_buf() };
    let json = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), source })?;
    let name = path.display().to_string();
    let config: T = parse(&json, &name)?;
    for key in config.unknown_keys() {
        eprintln!("warning: {name}: unknown {} config key `{key}` (kept, not used)", T::KIND);
    }
    Ok(config)
}
