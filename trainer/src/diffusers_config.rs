//! Reading diffusers `config.json` files into serde structs whose fields use the upstream names:
//! parse, validate (errors name the file and field), and report keys the struct does not know
//! (kept in its `extra` map, never silently dropped); and writing them back as diffusers'
//! `save_config` does, with those keys kept.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::error::{Error, Result};

/// The diffusers version written into saved configs (`_diffusers_version`): the release whose
/// modules this crate mirrors and whose `from_pretrained` the tests load our output with.
pub const DIFFUSERS_VERSION: &str = "0.42.1";

/// A diffusers configuration struct.
pub trait DiffusersConfig: DeserializeOwned {
    /// What the config describes, for messages ("VAE", "scheduler").
    const KIND: &'static str;
    /// The classes (`_class_name`) a file of this kind may name.
    const CLASS_NAMES: &'static [&'static str];
    /// File name inside a model folder (`config.json`, `scheduler_config.json`).
    const FILE_NAME: &'static str;

    /// Rejects invalid values and combinations of the fields, naming the field; `source_name`
    /// names the file.
    fn validate_fields(&self, source_name: &str) -> Result<()>;

    /// Checks the class name the file gives (if any) and then the fields: what every config read
    /// passes through, as diffusers' `ConfigMixin` checks a config before building from it.
    fn validate(&self, source_name: &str) -> Result<()> {
        if let Some(class) = self.extra().get("_class_name").and_then(|v| v.as_str())
            && !Self::CLASS_NAMES.contains(&class)
        {
            let expected = match Self::CLASS_NAMES {
                [one] => format!("`{one}`"),
                many => format!("one of {many:?}"),
            };
            return Err(Error::InvalidConfig {
                source_name: source_name.to_string(),
                field: "_class_name".to_string(),
                reason: format!("is `{class}`, expected {expected}"),
            });
        }
        self.validate_fields(source_name)
    }

    /// Keys the struct does not know, as parsed.
    fn extra(&self) -> &BTreeMap<String, serde_json::Value>;

    /// Values diffusers accepts and this port computes the way diffusers does, but which do not
    /// mean what they say (a ratio the levels cannot give): printed as warnings when a file is
    /// read, never refused.
    fn warnings(&self) -> Vec<String> {
        Vec::new()
    }

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

    /// The config as diffusers' `save_config` writes it: the fields, the keys this struct does
    /// not know (kept from the file it was read from), `_class_name` (`class_name`, one of
    /// [`DiffusersConfig::CLASS_NAMES`]) and `_diffusers_version`.
    fn to_json_string(&self, class_name: &str) -> Result<String>
    where
        Self: Serialize,
    {
        to_json_string(self, class_name)
    }
}

/// The error for field `field` of the config read from `source_name`, for
/// [`DiffusersConfig::validate_fields`].
pub fn field_error(source_name: &str) -> impl Fn(&str, String) -> Error + '_ {
    move |field, reason| Error::InvalidConfig { source_name: source_name.to_string(), field: field.to_string(), reason }
}

/// Refuses the first of `sizes` (field, value) that is not positive, naming its field.
pub fn require_positive(source_name: &str, sizes: &[(&str, i64)]) -> Result<()> {
    match sizes.iter().find(|(_, value)| *value <= 0) {
        Some((field, value)) => Err(field_error(source_name)(field, format!("must be positive, got {value}"))),
        None => Ok(()),
    }
}

/// [`DiffusersConfig::to_json_string`].
pub fn to_json_string<T: DiffusersConfig + Serialize>(config: &T, class_name: &str) -> Result<String> {
    let bad = |reason: String| Error::InvalidArgument { name: format!("{} config", T::KIND), reason };
    if !T::CLASS_NAMES.contains(&class_name) {
        return Err(bad(format!("class `{class_name}` is not one of {:?}", T::CLASS_NAMES)));
    }
    let mut json = serde_json::to_value(config).map_err(|e| bad(format!("cannot serialise: {e}")))?;
    let map = json.as_object_mut().ok_or_else(|| bad("does not serialise to a JSON object".to_string()))?;
    map.insert("_class_name".to_string(), class_name.into());
    map.insert("_diffusers_version".to_string(), DIFFUSERS_VERSION.into());
    Ok(serde_json::to_string_pretty(&json).expect("a JSON value serialises"))
}

/// The `_class_name` of a diffusers config file (or of `file_name` in a folder), if it has one:
/// what selects the model family before the file is read as that family's config.
pub fn class_name(path: &Path, file_name: &str) -> Result<Option<String>> {
    let path = if path.is_dir() { path.join(file_name) } else { path.to_path_buf() };
    let json = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), error: source })?;
    let value: serde_json::Value = serde_json::from_str(&json).map_err(|e| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: "(json)".to_string(),
        reason: e.to_string(),
    })?;
    match value.get("_class_name") {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(serde_json::Value::String(class)) => Ok(Some(class.clone())),
        Some(other) => Err(Error::InvalidConfig {
            source_name: path.display().to_string(),
            field: "_class_name".to_string(),
            reason: format!("must be a string, got {other}"),
        }),
    }
}

/// Parses and validates a config; `source_name` names it in errors. A value of the wrong type
/// is reported with its key (`field `block_out_channels``), not only a line and column.
pub fn parse<T: DiffusersConfig>(json: &str, source_name: &str) -> Result<T> {
    let bad =
        |field: String, reason: String| Error::InvalidConfig { source_name: source_name.to_string(), field, reason };
    let value: serde_json::Value = serde_json::from_str(json).map_err(|e| bad("(json)".to_string(), e.to_string()))?;
    let config: T = match T::deserialize(&value) {
        Ok(config) => config,
        Err(e) => {
            let message = e.to_string();
            return Err(match offending_key::<T>(&value, &message) {
                Some(key) => {
                    let found = value.get(&key).map(|v| v.to_string()).unwrap_or_default();
                    bad(key, format!("{message} (found {found})"))
                }
                None => bad("(json)".to_string(), message),
            });
        }
    };
    config.validate(source_name)?;
    Ok(config)
}

/// The key a deserialisation error is about: the field a "missing field" message names, else the
/// first top-level key whose value alone does not deserialise (every diffusers config struct
/// fills the other fields with defaults, so a one-key object isolates the bad value; JSON
/// positions do not, since flattened structs are buffered before they are read).
fn offending_key<T: DeserializeOwned>(value: &serde_json::Value, message: &str) -> Option<String> {
    if let Some(missing) = message.strip_prefix("missing field `").and_then(|m| m.split('`').next()) {
        return Some(missing.to_string());
    }
    let object = value.as_object()?;
    object.iter().find_map(|(key, v)| {
        let alone = serde_json::Value::Object(serde_json::Map::from_iter([(key.clone(), v.clone())]));
        T::deserialize(&alone).err().filter(|e| !e.to_string().starts_with("missing field")).map(|_| key.clone())
    })
}

/// Reads a config file (or the [`DiffusersConfig::FILE_NAME`] in a folder); unknown keys and
/// [`DiffusersConfig::warnings`] are printed to stderr.
pub fn read<T: DiffusersConfig>(path: &Path) -> Result<T> {
    let (config, warnings) = read_quiet::<T>(path)?;
    for warning in warnings {
        eprintln!("warning: {warning}");
    }
    Ok(config)
}

/// [`read`] returning the warnings instead of printing them (for checks that run before the
/// file is read again to build the model, so each warning is printed once).
pub fn read_quiet<T: DiffusersConfig>(path: &Path) -> Result<(T, Vec<String>)> {
    let path = if path.is_dir() { path.join(T::FILE_NAME) } else { path.to_path_buf() };
    let json = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), error: source })?;
    let name = path.display().to_string();
    let config: T = parse(&json, &name)?;
    let mut warnings: Vec<String> = config
        .unknown_keys()
        .iter()
        .map(|key| format!("{name}: unknown {} config key `{key}` (kept, not used)", T::KIND))
        .collect();
    warnings.extend(config.warnings().into_iter().map(|w| format!("{name}: {w}")));
    Ok((config, warnings))
}
